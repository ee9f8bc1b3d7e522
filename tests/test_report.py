"""`freeze report`: the HTML page of a real synthtiny run, read back with the stdlib HTML
parser and opened in headless Chromium."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from conftest import current_dir
from pipeline.views.html import CORRECT_MSSD_FRAC, PANEL_SIZE, choose_samples, worst_samples

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SAMPLES = 4


def _table(rows: list[tuple[int, int, bool]]) -> pd.DataFrame:
    """An estimate table (as ``estimate_table`` returns) of (obj_id, im_id, correct) rows."""
    return pd.DataFrame({"scene_id": 1, "im_id": [r[1] for r in rows], "obj_id": [r[0] for r in rows],
                         "est_id": 0, "correct": [r[2] for r in rows]})


def test_choose_samples_spreads_over_objects_and_mixes_correct_and_wrong():
    table = _table([(1, 0, True), (1, 1, True), (1, 2, True),   # object 1: three correct
                    (2, 0, False), (2, 1, False),               # object 2: two wrong
                    (3, 0, True), (3, 1, False)])               # object 3: one of each
    # Turns: obj 1 correct (0 <= 0), obj 2 wrong (1 > 0), obj 3 correct (1 <= 1), obj 1 has
    # no wrong one left to balance, so another correct one.
    got = choose_samples(table, 4)
    assert list(got.obj_id) == [1, 1, 2, 3]
    assert list(got.correct) == [True, True, False, True]
    again = choose_samples(table.sample(frac=1.0, random_state=3), 4)
    assert got.index.tolist() == again.index.tolist()  # independent of the table's order
    assert len(choose_samples(table, 100)) == len(table)
    assert choose_samples(table, 0).empty and choose_samples(table.iloc[:0], 5).empty
    # Objects 2 and 3 alone: wrong (no correct one in object 2), correct, wrong.
    got = choose_samples(table[table.obj_id > 1], 3)
    assert sorted(got.correct.tolist()) == [False, False, True]


def test_worst_samples_are_the_farthest_wrong_estimates_spread_over_objects():
    table = _table([(1, 0, False), (1, 1, False), (1, 2, False), (2, 0, False), (2, 1, True), (3, 0, False)])
    table["mssd_frac"] = [3.0, 2.0, 1.5, 0.4, 0.05, np.nan]  # object 3's estimate has no ground truth to match
    table["score"] = [0.1, 0.9, 0.5, 0.5, 0.5, 0.2]
    got = worst_samples(table, 4)
    # the unmatched one first, then object 1's two farthest (half of 4), then object 2's wrong one
    assert list(zip(got.obj_id, got.im_id)) == [(3, 0), (1, 0), (1, 1), (2, 0)]
    assert not got.correct.any() and "_far" not in got.columns
    assert worst_samples(table, 0).empty and len(worst_samples(table, 10)) == 5


def _app() -> typer.Typer:
    """The real `freeze` app (the commands' wiring is part of what is tested)."""
    from pipeline.commands.cli import app

    return app


class _Page(HTMLParser):
    """Tables (by class: rows of {data-key: text}), images, and sample figures' classes."""

    def __init__(self):
        super().__init__()
        self.tables: dict[str, list[dict[str, str]]] = {}
        self.images: list[str] = []
        self.figures: list[str] = []
        self.captions: list[str] = []
        self._table = None
        self._row = None
        self._cell = None
        self._in_caption = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(a.get("class", ""), [])
        elif tag == "tr" and self._table is not None:
            self._row = {}
        elif tag == "td" and self._row is not None:
            self._cell = a.get("data-key", "")
            self._row[self._cell] = ""
        elif tag == "img":
            self.images.append(a.get("src", ""))
        elif tag == "figure":
            self.figures.append(a.get("class", ""))
        elif tag == "figcaption":
            self._in_caption = True
            self.captions.append("")

    def handle_endtag(self, tag):
        if tag == "table":
            self._table = None
        elif tag == "tr" and self._row is not None:
            if self._row:  # header rows have no td
                self._table.append(self._row)
            self._row = None
        elif tag == "td":
            self._cell = None
        elif tag == "figcaption":
            self._in_caption = False

    def handle_data(self, data):
        if self._cell is not None:
            self._row[self._cell] += data
        if self._in_caption:
            self.captions[-1] += data


@pytest.fixture(scope="module")
def tiny_report(tiny_run):
    """The session's synthtiny run (tests/conftest.py), and its report written by `freeze report`."""
    work, _ = tiny_run
    env = {"FREEZE_CACHE": str(work / "cache"), "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1",
           "FREEZE_RUN_JSON": None}
    t0 = time.perf_counter()
    result = CliRunner().invoke(_app(), ["report", "--dataset", "synthtiny", "--config", "datasets=synthtiny",
                                         "--samples", str(SAMPLES)], env=env)
    seconds = time.perf_counter() - t0
    assert result.exit_code == 0, (result.output, result.exception)
    page = work / "results" / "report_synthtiny.html"  # the default place: <cache parent>/results
    assert page.exists(), result.output
    return work, page, seconds


def _artifact(work: Path, stage: str, pattern: str) -> list[Path]:
    """Files of the default run's ``stage`` folder (``pattern`` starts with the
    signature level, ``*/``): the session's cache also holds other configurations'."""
    assert pattern.startswith("*/")
    return sorted(current_dir(work, stage).glob(pattern[2:]))


@pytest.mark.slow
def test_report_holds_the_scores_tables_and_images(tiny_report):
    work, page_path, seconds = tiny_report
    assert seconds < 60, f"the report took {seconds:.1f} s"
    text = page_path.read_text(encoding="utf-8")
    # Self-contained: no external stylesheet, script or image.
    assert not re.search(r"<(link|script)\b", text)
    assert not re.search(r'src="(?!data:)', text)
    page = _Page()
    page.feed(text)
    scores = json.loads(_artifact(work, "score", "*/all/scores.json")[0].read_text())
    summary = scores["summary"]

    [row] = page.tables["summary"]
    for key in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD"):
        assert row[key] == f"{summary[key]:.3f}"
    assert row["n_targets"] == str(summary["n_targets"])
    assert row["n_estimates"] == str(summary["n_estimates"])

    per_obj = page.tables["per-object"]
    assert [int(r["obj_id"]) for r in per_obj] == [int(o["obj_id"]) for o in scores["per_object"]]
    for r, o in zip(per_obj, scores["per_object"]):
        assert r["AR"] == f"{o['AR']:.3f}"
        assert r["n_targets"] == str(o["n_targets"])

    # Correct estimates per object, recomputed from errors.parquet and models_info.json:
    # MSSD to the nearest valid GT instance <= 0.2 x diameter.
    errors = pd.read_parquet(_artifact(work, "score", "*/all/errors.parquet")[0])
    errors = errors[errors.gt_valid]
    best = errors.groupby(["scene_id", "im_id", "obj_id", "est_id"]).mssd.min().reset_index()
    info_path = _artifact(work, "synth", "*/dataset/synthtiny/models/models_info.json")[0]
    diam = {int(k): v["diameter"] for k, v in json.loads(info_path.read_text()).items()}
    best["correct"] = best.mssd <= CORRECT_MSSD_FRAC * best.obj_id.map(diam)
    for r in per_obj:
        b = best[best.obj_id == int(r["obj_id"])]
        assert r["correct"] == (f"{int(b.correct.sum())} / {len(b)}" if len(b) else "-")

    # Time per stage: one row per stage, jobs as many as the stage's manifests.
    timing = {r["stage"]: r for r in page.tables["timing"]}
    assert list(timing) == ["synth", "render_templates", "symmetries", "model_features", "segment_prior",
                            "scene_features", "register", "refine", "score"]
    n_obj = len(_artifact(work, "render_templates", "*/obj_*/_manifest.json"))
    n_scene = len(_artifact(work, "scene_features", "*/scene_*/_manifest.json"))
    assert n_obj == 3 and n_scene == 1  # synthtiny: 3 objects, 1 scene
    assert int(timing["render_templates"]["jobs"]) == n_obj
    assert int(timing["refine"]["jobs"]) == n_scene + 1  # per scene, and the dataset's results CSV
    assert int(timing["score"]["jobs"]) == 1
    shares = [float(r["share"].rstrip("%")) for r in timing.values()]
    assert sum(shares) == pytest.approx(100, abs=0.5)

    # Hypotheses: per source, as many as refine's hypotheses.parquet holds, and those chosen.
    hyps = pd.concat([pd.read_parquet(p) for p in _artifact(work, "refine", "*/scene_*/hypotheses.parquet")])
    rows = {r["source"]: r for r in page.tables["hypotheses"]}
    assert set(rows) == set(hyps.source)
    for source, g in hyps.groupby("source"):
        assert rows[source]["hypotheses"] == str(len(g)) and rows[source]["chosen"] == str(int(g.chosen.sum()))
    assert {int(r["obj_id"]) for r in page.tables["modality-signal"]} <= set(hyps.obj_id.astype(int))

    # Images: the visibility plot, the timing chart, the samples, the hypotheses, one SAR figure per object.
    sar_objs = set()
    for p in _artifact(work, "refine", "*/scene_*/sar.parquet"):
        sar_objs |= set(pd.read_parquet(p).obj_id.astype(int))
    n_samples = min(SAMPLES, len(best))
    assert len(page.images) == 2 + n_samples + 1 + len(sar_objs)
    sizes = []
    from PIL import Image

    for src in page.images:
        assert src.startswith("data:image/png;base64,")
        raw = base64.b64decode(src.split(",", 1)[1], validate=True)
        assert raw[:8] == PNG_SIGNATURE
        with Image.open(io.BytesIO(raw)) as im:
            im.load()
            assert im.format == "PNG" and im.width >= 200 and im.height >= 200
            sizes.append(im.size)
    # Each sample is the estimate and the ground truth side by side, PANEL_SIZE px each.
    assert sizes[2:2 + n_samples] == [(2 * PANEL_SIZE + 6, PANEL_SIZE)] * n_samples

    # The sample spreads over the objects and mixes correct and wrong estimates.
    samples = [f for f in page.figures if f.startswith("sample")]
    assert len(samples) == n_samples
    kinds = {f.split()[1] for f in samples}
    expected = {k for k, present in (("correct", best.correct.any()), ("wrong", (~best.correct).any())) if present}
    assert kinds == expected
    sample_objs = {int(m.group(1)) for c in page.captions if (m := re.match(r"object (\d+), scene", c))}
    assert sample_objs == set(best.obj_id.astype(int))  # 4 samples, 3 objects with estimates
    assert f"at most {CORRECT_MSSD_FRAC:g} × its diameter" in text


@pytest.mark.slow
def test_report_command_names_the_missing_scores(tiny_report):
    work, _, _ = tiny_report
    env = {"FREEZE_CACHE": str(work / "cache"), "PYOPENGL_PLATFORM": "egl", "FREEZE_RUN_JSON": None}
    out = work / "other.html"
    result = CliRunner().invoke(_app(), ["report", "--dataset", "synthtiny", "--config", "datasets=synthtiny",
                                         "--config", "visual=colortex-coarse", "--out", str(out)], env=env)
    assert result.exit_code == 2
    assert "scores.json" in result.output and "not scored yet" in result.output
    assert not out.exists()
    # The run Snakemake passes in $FREEZE_RUN_JSON wins over the default manifest.
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan

    other = RunPlan(load_run({"datasets": "synthtiny", "visual": "colortex-coarse"}), cache=work / "cache")
    missing = other["synthtiny"]["score"].item_dir("all") / "scores.json"
    result = CliRunner().invoke(_app(), ["report", "--dataset", "synthtiny", "--out", str(out)],
                                env={**env, "FREEZE_RUN_JSON": other.to_json()})
    assert result.exit_code == 2
    assert str(missing) in result.output


@pytest.mark.slow
def test_show_hypotheses_draws_each_hypothesis_of_a_candidate(tiny_report, tmp_path):
    work, _, _ = tiny_report
    env = {"FREEZE_CACHE": str(work / "cache"), "PYOPENGL_PLATFORM": "egl", "FREEZE_RUN_JSON": None}
    hyps = pd.concat([pd.read_parquet(p) for p in _artifact(work, "refine", "*/scene_*/hypotheses.parquet")])
    cand = int(hyps.groupby("cand_id").size().idxmax())
    result = CliRunner().invoke(_app(), ["show", "hypotheses", "--dataset", "synthtiny", "--scene", "1",
                                         "--candidate", str(cand), "--out", str(tmp_path)], env=env)
    assert result.exit_code == 0, result.output
    png = tmp_path / f"hypotheses_synthtiny_scene_000001_cand_{cand}.png"
    from PIL import Image

    with Image.open(png) as im:  # one panel per hypothesis, side by side
        n = int((hyps.cand_id == cand).sum())
        assert im.width >= 240 * n and im.height >= 240
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan
    from pipeline.views.hypotheses_figure import hypothesis_cases

    plan = RunPlan(load_run({"datasets": "synthtiny"}), cache=work / "cache")["synthtiny"]
    (case,) = hypothesis_cases(plan, scene_id=1, cand_id=cand)
    assert len(case.panels) == n and sum(p.chosen for p in case.panels) == 1
    result = CliRunner().invoke(_app(), ["show", "hypotheses", "--dataset", "synthtiny", "--candidate", "99999",
                                         "--out", str(tmp_path)], env=env)
    assert result.exit_code == 2 and "candidate 99999 has no hypotheses" in result.output


CHECK_SCRIPT = """<script>
window.__errors = [];
window.addEventListener("error", function (e) {
  var t = e.target && e.target.tagName ? " on <" + e.target.tagName + ">" : "";
  window.__errors.push(String(e.message || e.type) + t);
}, true);
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var out = document.createElement("pre");
  out.id = "report-check";
  out.textContent = JSON.stringify({
    images: imgs.length,
    loaded: imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length,
    shown: imgs.filter(function (i) { return i.getBoundingClientRect().width > 0; }).length,
    errors: window.__errors
  });
  document.body.appendChild(out);
});
</script>"""


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _run_chromium(*args: str) -> subprocess.CompletedProcess:
    cmd = [_chromium(), "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180)


@pytest.mark.slow
def test_report_renders_in_chromium(request, tmp_path):
    if not _chromium():
        pytest.skip("no chromium binary (Debian package 'chromium') on PATH")
    work, page_path, _ = request.getfixturevalue("tiny_report")  # only built when a browser is there
    parsed = _Page()
    parsed.feed(page_path.read_text(encoding="utf-8"))
    n_images = len(parsed.images)
    kinds = {f.split()[1] for f in parsed.figures if f.startswith("sample")}
    # A copy of the page with a check that writes what the browser saw into the DOM.
    probe = tmp_path / "probe.html"
    probe.write_text(page_path.read_text(encoding="utf-8").replace("</head>", CHECK_SCRIPT + "\n</head>", 1),
                     encoding="utf-8")
    proc = _run_chromium("--virtual-time-budget=10000", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="report-check">(.*?)</pre>', proc.stdout, re.S)
    assert m, (proc.stdout[-2000:], proc.stderr[-2000:])
    check = json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))
    assert check["errors"] == []
    assert check["images"] == check["loaded"] == check["shown"] == n_images

    # A screenshot of the whole page (kept beside the run for a look): it is not blank,
    # and the sample frames show both the green (correct) and the red (wrong) outline.
    shot = work / "results" / "report_synthtiny.png"
    proc = _run_chromium(f"--screenshot={shot}", "--window-size=1200,6000", page_path.as_uri())
    assert shot.exists(), proc.stderr[-2000:]
    from PIL import Image

    with Image.open(shot) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    assert rgb.shape == (6000, 1200, 3)
    assert rgb.std() > 20

    def has(colour):  # a frame colour of the page's style sheet, exactly
        return bool((np.abs(rgb - np.array(colour)).sum(axis=-1) <= 6).sum() > 500)

    assert has((0x28, 0xC8, 0x3C)) == ("correct" in kinds)
    assert has((0xE6, 0x28, 0x28)) == ("wrong" in kinds)


# ------------------------------------------------------------ empty, NaN and inf inputs
# The report is built from whatever the artifacts hold. These tests build its inputs
# (scores.json, the estimate table, stage manifests, refine's tables, SAR cases) with
# empty, all-NaN and infinite columns around a stand-in plan, and check that the page
# and every figure are still produced, with "no data" where nothing can be drawn.

NAN, INF = float("nan"), float("inf")


def _png_ok(png: bytes) -> None:
    from PIL import Image

    assert png[:8] == PNG_SIGNATURE
    with Image.open(io.BytesIO(png)) as im:
        im.load()
        assert im.width > 50 and im.height > 50


class _Stage:
    """What the report reads of a stage plan: name, signature, folder, item folders, and
    the artifacts by name (their file names from the stage's declaration, as
    :class:`pipeline.workflow.plan.StagePlan` has them)."""

    def __init__(self, root: Path, stage: str):
        self.stage, self.signature, self.dir = stage, f"{stage}-00000000", root / stage / f"{stage}-00000000"

    def item_dir(self, item: str) -> Path:
        return self.dir / item

    def path(self, item: str, name: str) -> Path:
        from pipeline.workflow.stage_graph import item_kind, spec

        return self.item_dir(item) / spec(self.stage).artifact(name, item_kind(item)).file

    def table(self, item: str, name: str) -> pd.DataFrame:
        from pipeline.common.store import read_table

        return read_table(self.path(item, name))

    def arrays(self, item: str, name: str, names: list[str] | None = None) -> dict:
        from pipeline.common.store import load_arrays

        return load_arrays(self.path(item, name), names)


class _Plan:
    """A stand-in dataset plan: stages under ``root``, no dataset behind it."""

    def __init__(self, root: Path, scene_ids: list[int]):
        from types import SimpleNamespace

        self.name = "fake"
        self.dataset = SimpleNamespace(kind="synthetic", split="test")
        self.obj_ids, self.scene_ids = [1, 2], scene_ids
        self.scene_items = [f"scene_{s:06d}" for s in scene_ids]
        self.results_csv_name = "freeze_fake-test.csv"
        self.stages = {s: _Stage(root, s) for s in ("synth", "refine", "register", "score")}

    def __getitem__(self, stage: str) -> _Stage:
        return self.stages[stage]


class _RunPlan:
    def __init__(self, root: Path, plan: _Plan):
        from types import SimpleNamespace

        self.plan, self.cache = plan, root / "cache"
        enc = {"manifest": "m", "signature": "s", "version": 1}
        self.encoders = {"geometric": enc, "visual": enc}
        self.run = SimpleNamespace(method="freeze", model_dump=lambda: {"method": "freeze"})

    def __getitem__(self, dataset: str) -> _Plan:
        return self.plan


def _manifest(path: Path, wall, peak) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # json.dumps writes NaN and inf as NaN / Infinity, which json.loads reads back
    path.write_text(json.dumps({"key": "k", "wall_time_s": wall, "peak_rss_mb": peak}))


def _scores(kind: str) -> dict:
    """scores.json: "empty" (no rows, None values) or "nonfinite" (NaN and inf)."""
    if kind == "empty":
        return {"summary": {"AR": None, "AR_VSD": None, "AR_MSSD": None, "AR_MSPD": None, "n_targets": 0,
                            "n_estimates": 0, "n_evaluated": 0, "mean_time_per_image": None, "notes": []},
                "recalls": {"vsd": [], "mssd": [], "mspd": []}, "per_object": [], "per_visibility": []}
    bins = [{"visib_min": i / 10, "visib_max": (i + 1) / 10, "n_targets": [None, NAN, INF, -3, 0][i % 5],
             "AR": [None, NAN, INF, -INF, NAN][i % 5], "AR_VSD": NAN, "AR_MSSD": None, "AR_MSPD": INF}
            for i in range(10)]
    bins.append({"visib_min": NAN, "visib_max": INF, "n_targets": 4, "AR": 0.5})  # a bin without edges
    return {"summary": {"AR": NAN, "AR_VSD": INF, "AR_MSSD": -INF, "AR_MSPD": None, "n_targets": 3,
                        "n_estimates": 5, "n_evaluated": 5, "mean_time_per_image": INF, "notes": ["x"]},
            "recalls": {"vsd": [[NAN] * 10, [INF] * 10], "mssd": [NAN] * 10, "mspd": [INF, None] + [NAN] * 7},
            "per_object": [{"obj_id": 1, "AR": NAN, "AR_VSD": INF, "AR_MSSD": None, "AR_MSPD": -INF,
                            "n_targets": NAN}, {"obj_id": None, "AR": 1.0}],
            "per_visibility": bins}


def _estimates(kind: str) -> pd.DataFrame:
    from pipeline.views.html import empty_estimate_table

    if kind == "empty":
        return empty_estimate_table()
    return pd.DataFrame({"scene_id": 1, "im_id": [0, 1, 2], "obj_id": [1, 1, 2], "est_id": 0,
                         "score": [NAN, INF, 0.5], "R": [np.eye(3)] * 3, "t": [np.zeros(3)] * 3,
                         "gt_id": [0, -1, 0], "mssd": [NAN, INF, 3.0], "mspd": [INF, NAN, 1.0],
                         "visib": [NAN, INF, 0.5], "diameter": [100.0, 0.0, NAN],
                         "mssd_frac": [NAN, INF, NAN], "correct": [False, False, True]})


def _fake_run(tmp_path: Path, kind: str, monkeypatch) -> _RunPlan:
    """A run whose artifacts hold ``kind`` ("empty" or "nonfinite") values."""
    from pipeline.workflow.plan import scene_item
    from pipeline.views import html, hypotheses_figure, sar_figure
    from pipeline.views.sar_figure import SarCase

    plan = _Plan(tmp_path / "cache" / "fake", scene_ids=[] if kind == "empty" else [1])
    if kind == "nonfinite":
        for i, (wall, peak) in enumerate([(NAN, INF), (INF, None), (None, NAN)]):
            _manifest(plan["register"].item_dir(f"scene_{i}") / "_manifest.json", wall, peak)
        _manifest(plan["refine"].item_dir("all") / "_manifest.json", 2.0, 100.0)
        refine = plan["refine"].item_dir(scene_item(1))
        refine.mkdir(parents=True)
        pd.DataFrame({"source": ["fused", "fused", "geometric"], "hyp": [0, 1, 0], "chosen": [True, False, False],
                      "verification": [NAN, INF, NAN], "obj_id": 1, "cand_id": 0}).to_parquet(
            plan["refine"].path(scene_item(1), "hypotheses"))
        pd.DataFrame({"obj_id": [1, 2], "variant": 0, "chosen": True}).to_parquet(plan["refine"].path(scene_item(1), "sar"))
        reg = plan["register"].item_dir(scene_item(1))
        reg.mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"status": "ok", "hyp": 0, "obj_id": [1, 1], "cand_id": [0, 1], "signal_geometric": [INF, 1.0],
                      "signal_visual": [NAN, -INF], "w_geometric": [NAN, NAN], "w_visual": [INF, 0.5]}).to_parquet(
            plan["register"].path(scene_item(1), "coarse_hypotheses"))

    def cases(plan, obj_id, limit=3):  # SAR similarities: none, all NaN, inf and NaN
        img = np.full((32, 32, 3), 128, np.uint8)
        mask = np.zeros((32, 32), bool)
        sims = {1: [np.array([]), np.array([NAN, NAN])], 2: [np.array([INF, NAN, 0.3, -INF])]}[obj_id]
        return [SarCase(img, img, mask, img, mask, s, chosen=min(1, len(s) - 1) if len(s) else 0, title="t")
                for s in sims]

    monkeypatch.setattr(sar_figure, "sar_cases", cases)
    monkeypatch.setattr(hypotheses_figure, "hypothesis_cases", lambda plan, limit=4: [])
    monkeypatch.setattr(html, "read_scores", lambda plan: _scores(kind))
    monkeypatch.setattr(html, "estimate_table", lambda plan: _estimates(kind))
    monkeypatch.setattr(html, "draw_samples", lambda plan, samples, size=PANEL_SIZE: [])  # no images to render on
    return _RunPlan(tmp_path, plan)


@pytest.mark.parametrize("kind", ["empty", "nonfinite"])
def test_report_is_written_from_empty_nan_and_inf_artifacts(tmp_path, monkeypatch, kind):
    from pipeline.views import html, plots

    notes = []
    real = plots.no_data_figure
    monkeypatch.setattr(plots, "no_data_figure", lambda note="", **kw: notes.append(note) or real(note, **kw))
    rp = _fake_run(tmp_path, kind, monkeypatch)
    out = html.write_report(rp, "fake", tmp_path / "results" / "report.html", samples=2)
    text = out.read_text(encoding="utf-8")
    page = _Page()
    page.feed(text)
    for src in page.images:
        _png_ok(base64.b64decode(src.split(",", 1)[1]))
    [row] = page.tables["summary"]
    assert row["AR"] == row["AR_VSD"] == row["AR_MSSD"] == row["AR_MSPD"] == "-"
    assert row["mean_time_per_image"] == "-"
    if kind == "empty":
        assert page.tables["per-object"] == [] and "no per-visibility breakdown" in text
        assert "SAR ran on no estimate" in text and "hypotheses" not in page.tables
        return
    # NaN/inf recalls are "-" (means over tau too), never "nan" or "inf" in a cell
    cells = [v for rows in page.tables.values() for r in rows for v in r.values()]
    assert not [c for c in cells if re.search(r"\b(nan|inf)\b", c, re.I)]
    assert {r["metric"] for r in page.tables["recall"]} == {"recall"}
    assert all(v == "-" for r in page.tables["recall"] for k, v in r.items() if k != "metric")
    [obj] = page.tables["per-object"]  # the row without an object is left out
    assert obj["obj_id"] == "1" and obj["AR"] == "-" and obj["correct"] == "0 / 2"
    # the bins hold no finite recall and no target: the visibility chart says "no data"
    assert any("no target in any visible-fraction bin" in n for n in notes)
    timing = {r["stage"]: r for r in page.tables["timing"]}
    assert timing["register"]["jobs"] == "3" and timing["register"]["wall_s"] == "-"
    assert timing["register"]["peak_rss_mb"] == "-" and timing["register"]["share"] == "0.0%"
    assert timing["refine"]["wall_s"] == "2.0" and timing["refine"]["share"] == "100.0%"
    [hyp] = [r for r in page.tables["hypotheses"] if r["source"] == "fused"]
    assert hyp["hypotheses"] == "2" and hyp["mean_score"] == "-"
    assert len([f for f in page.figures if f == "sar"]) == 2  # both objects' SAR figures drawn


def test_visibility_figure_takes_empty_nan_and_inf_bins(monkeypatch):
    from pipeline.views import plots

    notes = []
    real = plots.no_data_figure
    monkeypatch.setattr(plots, "no_data_figure", lambda note="", **kw: notes.append(note) or real(note, **kw))
    full = [{"visib_min": i / 10, "visib_max": (i + 1) / 10, "n_targets": 2, "AR": 0.1 * i, "AR_VSD": 0.2,
             "AR_MSSD": 0.3, "AR_MSPD": 0.4} for i in range(10)]
    cases = {
        "no bins": [],
        "no edges": [{"visib_min": None, "visib_max": NAN, "n_targets": 3, "AR": 0.5}],
        "all NaN": [{**b, "n_targets": NAN, "AR": NAN, "AR_VSD": NAN, "AR_MSSD": NAN, "AR_MSPD": NAN} for b in full],
        "inf": [{**b, "n_targets": INF, "AR": INF, "AR_VSD": -INF} for b in full],
        "counts only": [{**b, "AR": None, "AR_VSD": None, "AR_MSSD": None, "AR_MSPD": None} for b in full],
        "some inf": [{**b, "AR": INF if i % 2 else b["AR"], "n_targets": INF if i == 3 else 2}
                     for i, b in enumerate(full)],
    }
    for name, bins in cases.items():
        _png_ok(plots.visibility_figure(bins, title=name))
    # nothing to draw at all: a figure saying so, not an empty chart
    assert len(notes) == 3 and all(n.startswith(plots.NO_DATA) for n in notes)


def test_timing_figure_takes_empty_nan_and_inf_values(monkeypatch):
    from pipeline.views import plots

    _png_ok(plots.timing_figure([], [], []))
    _png_ok(plots.timing_figure(["a", "b"], [NAN, NAN], [NAN, NAN]))
    _png_ok(plots.timing_figure(["a", "b", "c"], [INF, 2.0, None], [-INF, INF, 300.0]))
    _png_ok(plots.timing_figure(["a"], [0.0], [0.0]))
    with pytest.raises(ValueError, match="2 stages but 1 wall times"):
        plots.timing_figure(["a", "b"], [1.0], [1.0, 2.0])


def test_sar_figure_takes_empty_nan_and_inf_similarities(tmp_path):
    from PIL import Image

    from pipeline.views.sar_figure import SarCase, draw_sar_figure

    img = np.full((24, 24, 3), 90, np.uint8)
    mask = np.zeros((24, 24), bool)
    mask[8:16, 8:16] = True
    sims = [np.array([]), np.array([NAN, NAN, NAN]), np.array([INF, -INF]), np.array([NAN, 0.4, INF, 0.2])]
    cases = [SarCase(img, img, mask, img, mask, s, chosen=1 if len(s) > 1 else 0, title=f"case {i}")
             for i, s in enumerate(sims)]
    out = draw_sar_figure(cases, tmp_path / "sar.png", title="degenerate")
    with Image.open(out) as im:
        assert im.height > 4 * 150
    out = draw_sar_figure([], tmp_path / "none.png")  # no case at all: an empty figure, not an error
    assert out.exists()


def test_features_figure_takes_nan_inf_and_empty_clouds(tmp_path):
    from PIL import Image

    from pipeline.views.features_figure import DPI, FIGSIZE, FeatureCase, draw_features_figure, pca_colours

    rng = np.random.default_rng(0)
    model = rng.normal(size=(60, 3)) * 30
    feats = rng.normal(size=(60, 8))
    bad_feats = feats.copy()
    bad_feats[:5] = NAN
    bad_feats[5, 2] = INF
    cm, cs, e = pca_colours(bad_feats, bad_feats[:10])
    assert np.all(cm[:6] == 0.5) and np.all(np.isfinite(cm)) and 0 < e <= 1
    # rows left out of the fit do not change the others' colours
    cm_good, _, _ = pca_colours(feats[6:], feats[:1])
    assert np.array_equal(cm[6:], cm_good)
    assert np.all(pca_colours(np.full((4, 3), NAN), np.zeros((2, 3)))[0] == 0.5)
    assert pca_colours(np.zeros((0, 3)), np.zeros((2, 3)))[1].shape == (2, 3)

    def case(scene_pts, scene_feats, model_pts=model, diameter=100.0, t=(0.0, 0.0, 600.0)):
        parts = {"geometric": (feats, scene_feats), "visual": (feats, scene_feats), "fused": (feats, scene_feats)}
        return FeatureCase(dataset="d", obj_id=1, scene_id=1, im_id=0, cand_id=0, model_points=model_pts,
                           scene_points=scene_pts, parts=parts, R=np.eye(3), t=np.array(t), diameter=diameter,
                           inlier_threshold=5.0)

    scene = model[:20] + np.array([0, 0, 600.0])
    nan_scene = scene.copy()
    nan_scene[::2] = NAN
    inf_model = model.copy()
    inf_model[:10] = INF
    variants = {
        "empty scene": case(np.zeros((0, 3)), np.zeros((0, 8))),
        "all-NaN scene": case(np.full((20, 3), NAN), feats[:20]),
        "NaN points and features": case(nan_scene, bad_feats[:20]),
        "inf model points, NaN diameter": case(scene, feats[:20], model_pts=inf_model, diameter=NAN),
        "nothing finite": case(np.full((5, 3), INF), feats[:5], model_pts=np.full((60, 3), NAN), diameter=INF),
        "inf pose": case(scene, feats[:20], t=(INF, 0.0, 600.0)),
    }
    for name, c in variants.items():
        out = draw_features_figure(c, tmp_path / f"{name}.png")
        with Image.open(out) as im:
            assert im.size == (round(FIGSIZE[0] * DPI), round(FIGSIZE[1] * DPI)), name


def test_recall_table_shows_dashes_for_missing_values():
    from pipeline.views.html import _recall_table

    page = _Page()
    page.feed(_recall_table({"vsd": [[NAN] * 10, [0.5] * 10, [INF] * 10], "mssd": [None] * 10, "mspd": [0.1, 0.2]}))
    vsd, mssd, mspd = page.tables["recall"]
    assert all(v == "0.50" for k, v in vsd.items() if k != "metric")  # the mean of the finite taus
    assert all(v == "-" for k, v in {**mssd, **mspd}.items() if k != "metric")  # none, or not 10 values
    assert _recall_table({"vsd": [], "mssd": None}) == ""


# ------------------------------------------------------------------- file modes


def _private_tmp(monkeypatch):
    """Make pipeline.common.published_files' atomic_path hand out temporary files created 0600, as
    a secure temp-file call does: the published file's mode must not depend on it."""
    import contextlib
    import os

    from pipeline.common import published_files as files
    from pipeline.common.store import atomic_path

    @contextlib.contextmanager
    def private(path):
        with atomic_path(path) as tmp:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            yield tmp

    monkeypatch.setattr(files, "atomic_path", private)


@pytest.mark.parametrize("private", [False, True], ids=["open", "private-tmp"])
def test_report_files_follow_the_umask(tmp_path, monkeypatch, umask_022, private):
    import os
    import stat

    from pipeline.views import html, plots

    if private:
        _private_tmp(monkeypatch)
    rp = _fake_run(tmp_path, "empty", monkeypatch)
    page = html.write_report(rp, "fake", tmp_path / "results" / "report_fake.html", samples=0)
    assert stat.S_IMODE(page.stat().st_mode) == 0o644
    fig = plots._plt().figure()
    png = plots.save_figure(fig, tmp_path / "results" / "figures" / "f.png")
    assert stat.S_IMODE(png.stat().st_mode) == 0o644
    from pipeline.common import published_files as files

    os.umask(0o027)  # another umask, read again: the mode follows it
    files.forget_umask()
    page = html.write_report(rp, "fake", tmp_path / "results" / "report_fake.html", samples=0)
    assert stat.S_IMODE(page.stat().st_mode) == 0o640
    assert sorted(p.name for p in page.parent.iterdir()) == ["figures", "report_fake.html"]  # no temporary left

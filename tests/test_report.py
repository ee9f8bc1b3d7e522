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
from pipeline.report.html import CORRECT_MSSD_FRAC, PANEL_SIZE, choose_samples

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


def _app() -> typer.Typer:
    """The real `freeze` app (the commands' wiring is part of what is tested)."""
    from pipeline.cli import app

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
    from pipeline.config import load_run
    from pipeline.plan import RunPlan

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
    from pipeline.config import load_run
    from pipeline.plan import RunPlan
    from pipeline.report.hypotheses_figure import hypothesis_cases

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

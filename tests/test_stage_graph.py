"""The stage graph is declared once (pipeline/workflow/stage_graph.py) and everything agrees with it:
the keys, the Snakemake inputs, what each stage actually opens, and
what each stage publishes (the layering is tests/test_layers.py)."""

from __future__ import annotations

import dataclasses
import shutil
import sys
from pathlib import Path

import pytest

from pipeline.common import config as cfg
from pipeline.workflow import stage_graph
from pipeline.workflow.plan import RunPlan, StageIO
from pipeline.workflow.stage_graph import STAGES, UndeclaredRead, check_graph


ROOT = Path(__file__).resolve().parent.parent


def _plan(cache: Path, **overrides):
    return RunPlan(cfg.load_run({"datasets": "synthtiny", **overrides}), cache=cache)["synthtiny"]


def test_declarations_are_consistent_and_checked():
    check_graph()
    # refine's key must cover everything refine reads: drop the upstream that covers
    # scene_features and model_features, and the check refuses the graph
    bad = dict(STAGES)
    bad["refine"] = dataclasses.replace(STAGES["refine"], keyed_by=("symmetries",))
    with pytest.raises(ValueError, match="refine: keyed by|no keyed upstream covers"):
        check_graph(bad)
    bad = dict(STAGES)
    bad["register"] = dataclasses.replace(STAGES["register"],
                                          reads={"scene": ("scene_features", "model_features", "refine")})
    with pytest.raises(ValueError, match="register: reads 'refine'"):
        check_graph(bad)


def test_keys_follow_the_declared_upstreams(tmp_path):
    plan = _plan(tmp_path)
    for name, spec in STAGES.items():
        sp = plan[name]
        assert sp.code_version == spec.code_version
        # a synthetic dataset has no real sample: its synth key has no "source"
        assert set(sp.upstream) == set(spec.keyed_by) - {"source"}, name
        for u in set(spec.keyed_by) - {"source"}:
            expected = plan.dataset_key if u == "dataset" and spec.side != "model" else (
                plan.models_key if u == "dataset" else plan.prior_key if u == "prior" else plan[u].key)
            assert sp.upstream[u] == expected, (name, u)


def test_snakemake_inputs_are_the_declared_reads(tmp_path):
    plan = _plan(tmp_path)
    objs = [f"obj_{o:06d}" for o in plan.obj_ids]
    got = set(map(str, plan.input_manifests("refine", "scene_000001")))
    want = {str(plan["register"].manifest("scene_000001")), str(plan["scene_features"].manifest("scene_000001")),
            str(plan["segment_prior"].manifest("all")), str(plan["synth"].manifest("dataset"))}
    want |= {str(plan[s].manifest(o)) for s in ("symmetries", "model_features") for o in objs}
    assert got == want
    collect = set(map(str, plan.input_manifests("refine", "all")))
    assert {str(plan[s].manifest(f"scene_{i:06d}")) for s in ("refine", "register", "scene_features")
            for i in plan.scene_ids} <= collect
    assert plan.input_manifests("score", "all") == [plan["refine"].manifest("all"), plan["synth"].manifest("dataset")]
    assert [str(p) for p in plan.input_manifests("model_features", objs[0])] == [
        str(plan["render_templates"].manifest(objs[0])), str(plan["synth"].manifest("dataset"))]
    # the Snakefile's rules are generated from the declarations: none is written out by
    # hand, and none names an upstream itself
    snakefile = (ROOT / "Snakefile").read_text()
    assert "for _r in stage_rules():" in snakefile and "input:\n            stage_inputs(r.stage, r.kind)," in snakefile
    for stage in STAGES:
        assert f"rule {stage}:" not in snakefile, stage
    assert not list((ROOT / "stages").glob("*.smk"))


def test_rules_follow_the_declarations():
    rules = stage_graph.stage_rules()
    assert [r.name for r in rules] == ["synth", "render_templates", "symmetries", "model_features", "segment_prior",
                                       "scene_features", "register", "refine", "refine_collect", "score"]
    assert {(r.stage, r.kind) for r in rules} == {(n, k) for n, s in STAGES.items() for k in s.items}
    assert stage_graph.rule_name("refine", "all") == "refine_collect"
    with pytest.raises(ValueError, match="no 'obj' items"):
        stage_graph.rule_name("refine", "obj")


@pytest.mark.slow
def test_snakemake_defines_one_rule_per_stage_and_kind(tmp_path):
    """Snakemake itself lists the generated rules (and bop_all), each stage rule
    described by its declaration's summary."""
    import os
    import subprocess

    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env["FREEZE_CACHE"] = str(tmp_path / "cache")
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s", str(ROOT / "Snakefile"),
                           "--directory", str(tmp_path), "--list-rules", "--config", "datasets=synthtiny"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    listed = {line.split(" ", 1)[0]: line for line in proc.stdout.splitlines() if line and not line.startswith(" ")}
    assert set(listed) >= {r.name for r in stage_graph.stage_rules()} | {"bop_all"}
    assert STAGES["symmetries"].summary in listed["symmetries"]


def test_side_and_file_helpers():
    """What freeze estimate runs (the model and scene sides) and the stages whose times
    per image the results CSV sums come from the declarations."""
    assert stage_graph.stages_of_side("model") == ("render_templates", "symmetries", "model_features")
    assert stage_graph.stages_of_side("scene") == ("segment_prior", "scene_features", "register", "refine")
    assert stage_graph.stages_of_side("evaluation") == ("score",)
    assert stage_graph.stages_of_side("dataset") == ("synth",)
    timed = stage_graph.stages_writing("image_times", "scene")
    assert timed == ("scene_features", "register", "refine")
    assert set(timed) <= set(STAGES["refine"].reads_for("all"))  # refine's results CSV may read them all
    assert set(stage_graph.stages_writing("features", "obj")) == {"model_features"}


def test_labels_and_parameters_are_declared():
    """Every stage's signature label and keyed parameters are its declaration's: the
    plan calls them (test_plan.py pins the keys they give)."""
    rp = RunPlan(cfg.load_run({"datasets": "synthtiny"}), cache=Path("/nonexistent-cache"))
    plan = rp["synthtiny"]
    ctx = stage_graph.PlanContext(run=plan.run, dataset=plan.dataset, encoder_entries=lambda: rp.encoders)
    for name, spec in STAGES.items():
        assert plan[name].signature == f"{spec.plan_label(ctx)}-{plan[name].key[:8]}", name
        assert plan[name].params == spec.plan_params(ctx), name
    # undeclared, they are the stage's name and its parameters in the run manifest
    bare = dataclasses.replace(STAGES["register"], label=None, params=None)
    assert bare.plan_label(ctx) == "register" and bare.plan_params(ctx) == plan.run.stages.register.model_dump()
    assert dataclasses.replace(STAGES["synth"], params=None).plan_params(ctx) == {}  # no parameters of its own


def test_stage_io_refuses_undeclared_reads_and_writes(tmp_path):
    plan = _plan(tmp_path)
    io = plan.io("register", "scene_000001")
    with pytest.raises(FileNotFoundError, match="scene_features/.*/scene_000001: this input artifact is not built"):
        io.input_dir("scene_features")  # declared, but not there: a clear error before any reader runs
    with pytest.raises(UndeclaredRead, match="register .* reads 'symmetries'"):
        io.input_dir("symmetries")
    with pytest.raises(UndeclaredRead, match="prior"):
        io.prior_paths
    with pytest.raises(ValueError, match="register items are scene"):
        plan.io("register", "obj_000002")
    io = plan.io("symmetries", "obj_000002")
    with pytest.raises(RuntimeError, match=r"wrote \['notes.txt'\]"):
        with io.publish() as w:
            (w.dir / "symmetries.json").write_text("{}")
            (w.dir / "notes.txt").write_text("not declared")
    assert not io.out.item_dir("obj_000002").exists()  # nothing published


def _resolve(dotted: str):
    """The object a dotted name points to: the longest importable module prefix, then attributes."""
    import importlib

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


def _calls_of(module_path: Path, function: str) -> set[str]:
    """The names called (``f(...)``, ``x.f(...)``) in ``function`` of a module, and in the
    module's own functions it calls (one level: ``run`` -> ``_collect``)."""
    import ast

    tree = ast.parse(module_path.read_text())
    funcs = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}

    def called(node: ast.AST) -> set[str]:
        out = set()
        for c in ast.walk(node):
            if isinstance(c, ast.Call):
                f = c.func
                out.add(f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else "")
        return out

    names = called(funcs[function])
    for helper in names & set(funcs):
        names |= called(funcs[helper])
    return names


def test_stage_modules_call_their_algorithm_one_hop_away():
    """Each stage's ``run`` calls the library function (or the estimator's method) its
    declaration names, directly: read from the module's syntax tree, not its docstring;
    every function the declarations name (the docs' stage table) exists."""
    import importlib

    for name, spec in STAGES.items():
        module = importlib.import_module(spec.module)
        for kind in spec.items:
            for dotted in spec.algorithms_for(kind):
                assert callable(_resolve(dotted)), dotted
        calls = _calls_of(Path(module.__file__), "run")
        parts = spec.algorithm.split(".")
        wanted = parts[-2:] if parts[-2][:1].isupper() else parts[-1:]  # Class.method: the class is made, the method called
        missing = [w for w in wanted if w not in calls]
        assert not missing, f"stages/{name}.py run() does not call {spec.algorithm} ({', '.join(missing)} not called)"


def test_the_one_hop_check_sees_what_run_calls():
    """The check reads calls, not names in the text: register's run makes an Estimator
    and calls its register, and only mentions register_candidates in its docstring."""
    root = Path(__file__).resolve().parent.parent
    calls = _calls_of(root / "stages" / "register.py", "run")
    assert {"Estimator", "register", "publish"} <= calls and "register_candidates" not in calls
    assert "_collect" in _calls_of(root / "stages" / "refine.py", "run")
    assert "write_results_csv" in _calls_of(root / "stages" / "refine.py", "run")  # through _collect, one level


# ------------------------------------------------------------- what stages really open


class _Opened:
    """Every file opened by Python (audit hook) or read as Parquet (pyarrow opens files
    in C++, past the hook) while ``active``."""

    def __init__(self):
        self.paths: list[Path] = []
        self.active = False

    def hook(self, event: str, args) -> None:
        if self.active and event == "open" and isinstance(args[0], (str, bytes, Path)):
            self.paths.append(Path(args[0] if not isinstance(args[0], bytes) else args[0].decode()))


def _owner(path: Path, plan, cache: Path) -> str | None:
    """What an opened path belongs to: a stage of the plan, 'dataset', 'prior', or None."""
    path = path.resolve()
    if any(path == p.resolve() for p in plan.prior_paths):
        return "prior"
    root = plan.root.resolve()
    if root in path.parents:
        return "dataset"
    ds_cache = (cache / plan.name).resolve()
    if ds_cache in path.parents:
        return path.relative_to(ds_cache).parts[0]
    return None


@pytest.mark.slow
def test_every_stage_opens_only_what_it_declares(tiny_run, tmp_path, monkeypatch):
    """Re-run one job of every stage on a copy of the main synthtiny run, recording every
    file each opens; each must be in its own output or in a declared read."""
    import pipeline.common.store as store
    from pipeline.workflow.stage_graph import run_stage

    work, _ = tiny_run
    cache = tmp_path / "cache"
    shutil.copytree(work / "cache", cache)
    plan = _plan(cache)
    opened = _Opened()
    sys.addaudithook(opened.hook)
    read_table = store.read_table

    def recording_read_table(path):
        if opened.active:
            opened.paths.append(Path(path))
        return read_table(path)

    import stages.refine, stages.register, stages.scene_features  # noqa: E401, F401  (bind their read_table first)
    import pipeline.workflow.plan

    ensure_sound = pipeline.workflow.plan.ensure_sound

    def unrecorded_check(folder):
        # Checking an input's checksums hashes every file of its artifact (the synthetic
        # dataset's includes the prior): that is not the stage reading them.
        active, opened.active = opened.active, False
        try:
            ensure_sound(folder)
        finally:
            opened.active = active

    monkeypatch.setattr(pipeline.workflow.plan, "ensure_sound", unrecorded_check)

    for module in list(sys.modules.values()):
        if getattr(module, "read_table", None) is read_table:
            monkeypatch.setattr(module, "read_table", recording_read_table)
    jobs = [("render_templates", "obj_000002"), ("symmetries", "obj_000005"), ("model_features", "obj_000006"),
            ("segment_prior", "all"), ("scene_features", "scene_000001"), ("register", "scene_000001"),
            ("refine", "scene_000001"), ("refine", "all"), ("score", "all")]
    assert {s for s, _ in jobs} == set(STAGES) - {"synth"}
    used: dict[str, set[str]] = {}
    for stage, item in jobs:
        opened.paths.clear()
        opened.active = True
        try:
            run_stage(plan, stage, item, progress=False)
        finally:
            opened.active = False
        owners = {_owner(p, plan, cache) for p in opened.paths} - {None}
        allowed = set(StageIO(plan, stage, item).spec.reads_for(stage_graph.item_kind(item))) | {stage}
        assert owners, (stage, "recorded nothing: the instrumentation is broken")
        assert owners <= allowed, (stage, item, sorted(owners - allowed))
        used.setdefault(stage, set()).update(owners)
    for stage, owners in used.items():  # each stage read something of every upstream it is keyed by
        assert set(STAGES[stage].keyed_by) <= owners, (stage, sorted(owners))

# FreeZe pipeline. Main job: `snakemake --cores 2 bop_all`.
# Output paths are computed from cache keys at DAG time (pipeline/workflow/plan.py), so a change
# of parameters, encoders or stage code versions builds new artifacts beside the old
# ones and reruns only the stages that depend on the change.
import os
import shlex
import sys

from snakemake.utils import min_version

min_version("9.0")

from pipeline.commands.common import USER_ERRORS
from pipeline.common.config import ManifestError, load_run
from pipeline.workflow.plan import RunPlan
from pipeline.commands.run import planned_manifests
from pipeline.workflow.stage_graph import STAGES, stage_rules
from pipeline.workflow.stage_docs import job_per
from pipeline.common.threads import ENV_VARS

try:
    RUN = load_run(config)      # manifests/runs/default.yaml + --config overrides
    PLAN = RunPlan(RUN)
    DATASETS = []
    for _ds in PLAN.dataset_names:
        _ok, _why = PLAN.available(_ds)
        if _ok:
            # Planned here, inside the try: a dataset's plan is built on first use, and a
            # missing or escaping prior found later, in a rule's input, is a traceback.
            PLAN[_ds]
            DATASETS.append(_ds)
            for _note in PLAN.notes(_ds):
                print(_note, file=sys.stderr)
        else:
            print(_why, file=sys.stderr)
    # Every output path below is a wildcard pattern: a brace in the cache's path would be
    # read as a wildcard of Snakemake's, and the rules would match nothing.
    # (results/ and logs/ sit beside the cache, so its path covers theirs.)
    if any(c in str(PLAN.cache) for c in "{}"):
        raise ManifestError(f"the cache folder {PLAN.cache} holds a brace ({{ or }}), which Snakemake reads as a "
                            "wildcard: set FREEZE_CACHE to a path without braces")
except USER_ERRORS as _e:       # a bad option or manifest: its one line, not a traceback
    print(f"error: {_e}", file=sys.stderr)
    sys.exit(1)
if not DATASETS:                # nothing to run is a failure, not an empty table
    print("error: no dataset of the run can be run (see above); nothing to do", file=sys.stderr)
    sys.exit(1)
# Jobs rebuild the plan from this variable. It is deliberately not a rule param:
# Snakemake reruns jobs whose params change, but a job's output path already encodes
# its key, so a change that does not alter a stage's key must not rerun it.
os.environ["FREEZE_RUN_JSON"] = PLAN.to_json()

envvars:
    "FREEZE_RUN_JSON",

CACHE = str(PLAN.cache)
RESULTS = os.path.join(os.path.dirname(CACHE), "results")
LOGS = os.path.join(os.path.dirname(CACHE), "logs")
PY = sys.executable


def shell_word(value):
    """``value`` (a path) as one word of a rule's shell command: quoted for the shell
    (a space, a quote or a ``;`` in the clone's or the cache's path must neither split
    the command nor run one), with its braces doubled, as Snakemake formats the command
    again. Values Snakemake fills in use its own quoting instead (``{log:q}``)."""
    return shlex.quote(str(value)).replace("{", "{{").replace("}", "}}")


def stage_shell(stage):
    """Shell command of a stage job: the same entry point as `freeze stage`, kept to the
    rule's threads (the variables for the numeric libraries that read them at start-up;
    `--threads` for torch and OpenCV, see pipeline/common/threads.py)."""
    limits = " ".join(f"{v}={{threads}}" for v in ENV_VARS)
    return (f"{limits} {shell_word(PY)} -m pipeline.commands.cli stage {shell_word(stage)} --dataset {{wildcards.ds:q}} "
            "--item {params.item:q} --expect-sig {wildcards.sig:q} --threads {threads} > {log:q} 2>&1")


def stage_plan(wc, stage):
    sp = PLAN[wc.ds][stage]
    if wc.sig != sp.signature:
        raise ValueError(f"{stage} of {wc.ds}: requested signature {wc.sig}, but the current plan's is {sp.signature}")
    return sp


def stage_inputs(stage, kind):
    """Input function of the rule running ``stage`` for items of ``kind``: the manifests
    of everything the stage's declaration (pipeline/workflow/stage_graph.py) says it reads."""
    def inputs(wc):
        item = {"obj": lambda: f"obj_{wc.obj}", "scene": lambda: f"scene_{wc.scene}"}.get(kind, lambda: kind)()
        return [str(p) for p in PLAN[wc.ds].input_manifests(stage, item)]
    return inputs


SIGNATURE_UNCHECKED = {"synth", "render_templates", "symmetries", "segment_prior"}
"""The stages whose rules have no ``check`` param (see ``rule_params``)."""


def rule_params(stage, kind):
    """The params of the rule running ``stage`` for items of ``kind``: the item, and for
    most stages ``check``, which refuses at DAG time a signature the plan does not have
    (every job checks it again, ``--expect-sig``). The stages of SIGNATURE_UNCHECKED
    have never had it, and must not get it: a new rule param reruns every job that has
    already run (Snakemake's params trigger), and a rerun synth rebuilds everything after it."""
    item = {"obj": lambda wc: f"obj_{wc.obj}", "scene": lambda wc: f"scene_{wc.scene}"}.get(kind, kind)
    if stage in SIGNATURE_UNCHECKED:
        return {"item": item}
    return {"item": item, "check": lambda wc: stage_plan(wc, stage).signature}


def stage_paths(stage, kind):
    """(output manifest, log) patterns of the rule running ``stage`` for items of ``kind``:
    ``<cache>/<ds>/<stage>/<sig>/<item>/_manifest.json`` and
    ``<logs>/<ds>/<stage>/<sig>/<item>.log``, or ``<logs>/<ds>/<stage>/<sig>.log`` for a
    stage with one dataset-wide item."""
    item = {"obj": "obj_{obj}", "scene": "scene_{scene}"}.get(kind, kind)
    single = len(STAGES[stage].items) == 1 and kind in ("all", "dataset")
    return (f"{CACHE}/{{ds}}/{stage}/{{sig}}/{item}/_manifest.json",
            f"{LOGS}/{{ds}}/{stage}/{{sig}}.log" if single else f"{LOGS}/{{ds}}/{stage}/{{sig}}/{item}.log")


wildcard_constraints:
    ds="[a-z0-9]+",
    sig="[A-Za-z0-9.+-]+",
    obj="[0-9]{6}",
    scene="[0-9]{6}(-[0-9]+)?",


def stage_rule(r):
    """Define the rule ``r`` (a :class:`pipeline.workflow.stage_graph.StageRule`). A
    function, not the body of a loop: Snakemake evaluates a rule's ``shell:`` expression
    again when the job runs, where a loop variable would hold the last rule's value."""
    output, log = stage_paths(r.stage, r.kind)

    rule:
        name: r.name
        input:
            stage_inputs(r.stage, r.kind),
        output:
            output,
        params:
            **rule_params(r.stage, r.kind),
        threads: STAGES[r.stage].threads
        resources:
            mem_mb=STAGES[r.stage].mem_mb,
            runtime=STAGES[r.stage].runtime_min,
        log:
            log,
        shell:
            stage_shell(r.stage)

    workflow.get_rule(r.name).docstring = (
        f"Stage {r.stage}, one job per {job_per(r.stage, r.kind)}: {STAGES[r.stage].summary}.")


# The stage rules: one per stage and item kind (stage_graph.stage_rules: the stage's
# name, `refine_collect` for refine's dataset-wide item), from the declarations.
for _r in stage_rules():
    stage_rule(_r)


# The AR table and the reports take seconds: on a cluster they run where Snakemake runs,
# not as a job of their own.
localrules:
    bop_all,


rule bop_all:
    """Every stage on every dataset of the run; prints and writes the AR table and
    writes each dataset's HTML report (results/report_<dataset>.html).

    It has no output file on purpose, so it runs on every call (about a second): the
    table is always that of the current run, and Snakemake cannot skip the stages of a
    new configuration because an older table looks up to date.

    Its inputs are the outputs of every job of the plan, not only the scores: Snakemake
    schedules only the jobs its targets need, and an existing score would otherwise keep
    an item that `freeze verify --repair` deleted upstream from being rebuilt. A rebuilt
    item is newer than its dependents' outputs, so they rerun too (Snakemake's mtime
    trigger), and give the same results from the same inputs.

    The default target (`snakemake` and `freeze run` without one): the stage rules are
    defined above it, in the main Snakefile, so it is not the first rule."""
    default_target: True
    input:
        [str(p) for p in planned_manifests(PLAN, DATASETS)],
    params:
        datasets=",".join(DATASETS),
        table=os.path.join(RESULTS, "ar_table.md"),
        results=RESULTS,
    log:
        os.path.join(LOGS, "bop_all.log"),
    shell:
        f"{shell_word(PY)} -m pipeline.commands.cli table --out {{params.table:q}} --csv-dir {{params.results:q}} > {{log:q}} 2>&1"
        + "".join(f" && {shell_word(PY)} -m pipeline.commands.cli report --dataset {shell_word(ds)} "
                  f"--out {shell_word(os.path.join(RESULTS, f'report_{ds}.html'))} >> {{log:q}} 2>&1" for ds in DATASETS)


onstart:
    # A SLURM profile on a machine without `sbatch`: one line before any job, not a
    # shell error per job (pipeline/workflow/cluster_submit.py).
    from pipeline.workflow.cluster_submit import missing_submitter

    _plugin = workflow.executor_plugin
    _why = missing_submitter(_plugin.name if _plugin is not None else None,
                             getattr(workflow.executor_settings, "submit_cmd", None))
    if not _why:  # a status command in a path with a space or a `;`, run unquoted by the executor
        from pipeline.workflow.cluster_submit import unquoted_status_command

        _why = unquoted_status_command(_plugin.name if _plugin is not None else None,
                                       getattr(workflow.executor_settings, "status_cmd", None))
    if _why:
        print(f"error: {_why}", file=sys.stderr)
        sys.exit(1)
    # Encoders standing in for the paper's: one line per run. Here, not at the top of the
    # file, which every cluster job parses again (jobs run without hooks); `freeze run`
    # prints it itself, with its own options, and sets FREEZE_STAND_IN_SHOWN.
    from pipeline.common.stand_in import stand_in_notice

    _notice = stand_in_notice(RUN.geometric_encoder, RUN.visual_encoder)
    if _notice and not os.environ.get("FREEZE_STAND_IN_SHOWN"):
        print(_notice, file=sys.stderr)


onsuccess:
    _table = os.path.join(RESULTS, "ar_table.md")
    if os.path.exists(_table):
        print("\nBOP19 average recall (" + _table + "):\n" + open(_table).read())

"""Pipeline stages: one module per stage with one entry point, ``run(plan, item)``.

A stage module reads its upstream artifacts (through ``plan.io(stage, item)``, which
refuses what the stage's declaration does not list), calls one library function that
holds the algorithm, and publishes its own artifact. Its declaration (code version,
items, reads, writes, and where its algorithm lives) is in
:mod:`pipeline.workflow.stage_graph`; bump the code version there whenever a change alters the
stage's output. Modules import their heavy dependencies inside ``run``.

:func:`pipeline.workflow.stage_graph.run_stage` runs a stage by its declaration, which
names its module here; this package imports nothing.
"""


"""FreeZe: training-free zero-shot 6D pose estimation, as a pipeline over BOP datasets.

The library is cut into layers, one package each; a module imports only from its own
layer and the layers below it (``tests/test_layers.py`` walks the packages and checks
every import, so a new module is checked the day it is added):

====  =====================  ==========================================================
 0    ``pipeline.common``    what every layer uses: the manifests' schemas (config), the
                             cache's storage (atomic writes, manifests, keys, arrays and
                             tables), progress bars, thread counts and work mappers
 1    ``pipeline.formats``   files defined by others: BOP datasets and results
                             (``formats.bop``), pretrained weight files
                             (``formats.weights``)
 2    ``pipeline.method``    the method: geometry, encoders, rendering, registration,
                             refinement (verification, selection, turns, ICP, SAR), the
                             model side, the scene side, the prior's candidates
 3    ``pipeline.evaluation`` what the method is measured with: the BOP scorer
                             (``evaluation.metrics``), the synthetic BOP datasets
                             (``evaluation.synth``)
 4    ``pipeline.workflow``  the run: the stage graph, the plan (keys, paths, inputs),
                             the artifacts' description, cluster submission
 5    ``pipeline.views``     pictures and pages made from artifacts (report, figures)
 6    ``pipeline.commands``  the ``freeze`` command line, one module per command group
====  =====================  ==========================================================

The stage runners (``stages/``) sit above the library: each reads its inputs through
the plan, calls one function of the method and publishes. No module here imports them;
``pipeline.workflow.stage_graph.run_stage`` runs one by the module name its declaration
gives.
"""

"""Layer 4: the run — the stage graph declared once (:mod:`.stage_graph`), the plan of a run
(:mod:`.plan`: keys, paths, inputs), what an artifact holds (:mod:`.artifacts`) and cluster
submission (:mod:`.cluster_submit`).
"""

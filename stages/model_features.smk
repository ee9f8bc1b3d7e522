rule model_features:
    """Geometric and lifted visual features of one object's sampled points."""
    input:
        stage_inputs("model_features", "obj"),
    output:
        f"{CACHE}/{{ds}}/model_features/{{sig}}/obj_{{obj}}/_manifest.json",
    params:
        item=lambda wc: f"obj_{wc.obj}",
        check=lambda wc: stage_plan(wc, "model_features").signature,
    threads: STAGES["model_features"].threads
    resources:
        mem_mb=STAGES["model_features"].mem_mb,
        runtime=STAGES["model_features"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/model_features/{{sig}}/obj_{{obj}}.log",
    shell:
        stage_shell("model_features")

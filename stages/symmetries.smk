rule symmetries:
    """Geometric symmetries of one object, estimated from its model."""
    input:
        stage_inputs("symmetries", "obj"),
    output:
        f"{CACHE}/{{ds}}/symmetries/{{sig}}/obj_{{obj}}/_manifest.json",
    params:
        item=lambda wc: f"obj_{wc.obj}",
    threads: STAGES["symmetries"].threads
    resources:
        mem_mb=STAGES["symmetries"].mem_mb,
        runtime=STAGES["symmetries"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/symmetries/{{sig}}/obj_{{obj}}.log",
    shell:
        stage_shell("symmetries")

rule render_templates:
    """R template views of one object."""
    input:
        stage_inputs("render_templates", "obj"),
    output:
        f"{CACHE}/{{ds}}/render_templates/{{sig}}/obj_{{obj}}/_manifest.json",
    params:
        item=lambda wc: f"obj_{wc.obj}",
    threads: STAGES["render_templates"].threads
    resources:
        mem_mb=STAGES["render_templates"].mem_mb,
        runtime=STAGES["render_templates"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/render_templates/{{sig}}/obj_{{obj}}.log",
    shell:
        stage_shell("render_templates")

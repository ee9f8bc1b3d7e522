rule refine:
    """ICP refinement of the selected poses of one scene."""
    input:
        stage_inputs("refine", "scene"),
    output:
        f"{CACHE}/{{ds}}/refine/{{sig}}/scene_{{scene}}/_manifest.json",
    params:
        item=lambda wc: f"scene_{wc.scene}",
        check=lambda wc: stage_plan(wc, "refine").signature,
    threads: STAGES["refine"].threads
    resources:
        mem_mb=STAGES["refine"].mem_mb,
        runtime=STAGES["refine"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/refine/{{sig}}/scene_{{scene}}.log",
    shell:
        stage_shell("refine")


rule refine_collect:
    """The BOP results CSV of the dataset, from every scene's refined poses."""
    input:
        stage_inputs("refine", "all"),
    output:
        f"{CACHE}/{{ds}}/refine/{{sig}}/all/_manifest.json",
    params:
        item="all",
        check=lambda wc: stage_plan(wc, "refine").signature,
    threads: STAGES["refine"].threads
    resources:
        mem_mb=STAGES["refine"].mem_mb,
        runtime=STAGES["refine"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/refine/{{sig}}/all.log",
    shell:
        stage_shell("refine")

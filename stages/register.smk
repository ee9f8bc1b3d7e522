rule register:
    """RANSAC on fused-feature matches for every candidate of one scene."""
    input:
        stage_inputs("register", "scene"),
    output:
        f"{CACHE}/{{ds}}/register/{{sig}}/scene_{{scene}}/_manifest.json",
    params:
        item=lambda wc: f"scene_{wc.scene}",
        check=lambda wc: stage_plan(wc, "register").signature,
    threads: STAGES["register"].threads
    resources:
        mem_mb=STAGES["register"].mem_mb,
        runtime=STAGES["register"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/register/{{sig}}/scene_{{scene}}.log",
    shell:
        stage_shell("register")

rule scene_features:
    """Lifted points and features of every candidate of one scene."""
    input:
        stage_inputs("scene_features", "scene"),
    output:
        f"{CACHE}/{{ds}}/scene_features/{{sig}}/scene_{{scene}}/_manifest.json",
    params:
        item=lambda wc: f"scene_{wc.scene}",
        check=lambda wc: stage_plan(wc, "scene_features").signature,
    threads: STAGES["scene_features"].threads
    resources:
        mem_mb=STAGES["scene_features"].mem_mb,
        runtime=STAGES["scene_features"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/scene_features/{{sig}}/scene_{{scene}}.log",
    shell:
        stage_shell("scene_features")

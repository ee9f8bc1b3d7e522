rule register:
    """RANSAC on fused-feature matches for every candidate of one scene."""
    input:
        models=lambda wc: [str(PLAN[wc.ds]["model_features"].manifest(obj_item(o))) for o in PLAN[wc.ds].obj_ids],
        scene=lambda wc: str(PLAN[wc.ds]["scene_features"].manifest(f"scene_{wc.scene}")),
    output:
        f"{CACHE}/{{ds}}/register/{{sig}}/scene_{{scene}}/_manifest.json",
    params:
        item=lambda wc: f"scene_{wc.scene}",
        check=lambda wc: stage_plan(wc, "register").signature,
    log:
        f"{LOGS}/{{ds}}/register/{{sig}}/scene_{{scene}}.log",
    shell:
        stage_shell("register")

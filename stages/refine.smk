rule refine:
    """ICP refinement of the selected poses of one scene."""
    input:
        register=lambda wc: str(PLAN[wc.ds]["register"].manifest(f"scene_{wc.scene}")),
        symmetries=lambda wc: [str(PLAN[wc.ds]["symmetries"].manifest(obj_item(o))) for o in PLAN[wc.ds].obj_ids],
    output:
        f"{CACHE}/{{ds}}/refine/{{sig}}/scene_{{scene}}/_manifest.json",
    params:
        item=lambda wc: f"scene_{wc.scene}",
        check=lambda wc: stage_plan(wc, "refine").signature,
    log:
        f"{LOGS}/{{ds}}/refine/{{sig}}/scene_{{scene}}.log",
    shell:
        stage_shell("refine")


rule refine_collect:
    """The BOP results CSV of the dataset, from every scene's refined poses."""
    input:
        lambda wc: [str(PLAN[wc.ds]["refine"].manifest(scene_item(s))) for s in PLAN[wc.ds].scene_ids],
    output:
        f"{CACHE}/{{ds}}/refine/{{sig}}/all/_manifest.json",
    params:
        item="all",
        check=lambda wc: stage_plan(wc, "refine").signature,
    log:
        f"{LOGS}/{{ds}}/refine/{{sig}}/all.log",
    shell:
        stage_shell("refine")

rule score:
    """BOP19 VSD, MSSD, MSPD and AR of the dataset's results CSV."""
    input:
        stage_inputs("score", "all"),
    output:
        f"{CACHE}/{{ds}}/score/{{sig}}/all/_manifest.json",
    params:
        item="all",
        check=lambda wc: stage_plan(wc, "score").signature,
    threads: STAGES["score"].threads
    resources:
        mem_mb=STAGES["score"].mem_mb,
        runtime=STAGES["score"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/score/{{sig}}.log",
    shell:
        stage_shell("score")

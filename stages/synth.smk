rule synth:
    """Generate a synthetic BOP dataset (synthetic datasets only)."""
    output:
        f"{CACHE}/{{ds}}/synth/{{sig}}/dataset/_manifest.json",
    params:
        item="dataset",
    threads: STAGES["synth"].threads
    resources:
        mem_mb=STAGES["synth"].mem_mb,
        runtime=STAGES["synth"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/synth/{{sig}}.log",
    shell:
        stage_shell("synth")

rule segment_prior:
    """Candidate masks from the localisation prior (top-k per image and object)."""
    input:
        stage_inputs("segment_prior", "all"),
    output:
        f"{CACHE}/{{ds}}/segment_prior/{{sig}}/all/_manifest.json",
    params:
        item="all",
    threads: STAGES["segment_prior"].threads
    resources:
        mem_mb=STAGES["segment_prior"].mem_mb,
        runtime=STAGES["segment_prior"].runtime_min,
    log:
        f"{LOGS}/{{ds}}/segment_prior/{{sig}}.log",
    shell:
        stage_shell("segment_prior")

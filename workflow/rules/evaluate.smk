# Evaluation (run.evaluate: auto | true | false): Q_front / Q_vc of every scene, and errors against
# ground-truth maps and views where the scene has them (synthetic scenes, held-out copies).


rule evaluate:
    input:
        scene=SCENE_MODEL,
        # the textures and their frames, not the assembled model: assembly settings do not matter
        summary=f"{R}/visibility/summary.json",
        textures=get_textures,
        config=STAGE_CFG["evaluate"],
    output:
        f"{R}/evaluation/metrics.json",
    params:
        stage_config=STAGE_TEXT["evaluate"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        results=lambda wc, input: Path(input.summary).parent.parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/evaluate.log",
    benchmark:
        f"{R}/benchmarks/evaluate/evaluate.tsv"
    threads: RUN["scene_threads"]
    resources:
        mem_mb=8000,
        runtime=60,
    shell:
        "OMP_NUM_THREADS={threads} difftex evaluate --quiet --scene {params.scene:q} --results {params.results} "
        "--config {input.config} --out {output} > {log} 2>&1"

# Evaluation (run.evaluate: auto | true | false): Q_front / Q_vc of every scene, and errors against
# ground-truth maps and views where the scene has them (synthetic scenes, held-out copies).


rule evaluate:
    input:
        scene=SCENE_MODEL,
        # the textures and their frames, not the assembled model: assembly settings do not matter
        summary=str(RES.visibility_summary),
        textures=get_textures,
        config=STAGE_CFG["evaluate"],
    output:
        str(RES.metrics),
    params:
        stage_config=STAGE_TEXT["evaluate"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        results=RES.root,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("evaluate")),
    benchmark:
        str(RES.benchmark("evaluate", "evaluate"))
    threads: RUN["scene_threads"]
    resources:
        mem_mb=8000,
        runtime=60,
    shell:
        "OMP_NUM_THREADS={threads} difftex evaluate --quiet --scene {params.scene:q} --results {params.results} "
        "--config {input.config} --out {output} > {log} 2>&1"

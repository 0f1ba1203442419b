# Photo filtering: sharpness, polygons seen and their angles, per photo; kept photos per polygon.


rule filter:
    input:
        scene=SCENE_INPUTS,
        config=STAGE_CFG["filter"],
    output:
        table=f"{R}/photos.json",
        csv=f"{R}/photos.csv",
    params:
        stage_config=STAGE_TEXT["filter"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/filter.log",
    benchmark:
        f"{R}/benchmarks/filter/filter.tsv"
    threads: RUN["scene_threads"]
    resources:
        mem_mb=lambda wc, input: jobs.scene_mem_mb(input.scene, RUN),
        runtime=60,
    shell:
        "OMP_NUM_THREADS={threads} difftex filter --quiet --scene {params.scene:q} "
        "--config {input.config} --out {output.table} > {log} 2>&1"

# Visibility masks of every polygon. A checkpoint: its summary tells the workflow the polygon ids
# (and their sizes and candidate photos), from which the per-polygon jobs are made.


checkpoint visibility:
    input:
        scene=SCENE_INPUTS,
        photos=f"{R}/photos.json",
        config=STAGE_CFG["visibility"],
    output:
        summary=f"{R}/visibility/summary.json",
    params:
        stage_config=STAGE_TEXT["visibility"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dir=lambda wc, output: Path(output.summary).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/visibility.log",
    benchmark:
        f"{R}/benchmarks/visibility/visibility.tsv"
    threads: RUN["scene_threads"]
    resources:
        mem_mb=lambda wc, input: jobs.scene_mem_mb(input.scene, RUN, factor=8.0),
        runtime=120,
    shell:
        "OMP_NUM_THREADS={threads} difftex visibility --quiet --scene {params.scene:q} "
        "--photos {input.photos} --config {input.config} --out-dir {params.out_dir} > {log} 2>&1"

# Visibility masks per spatial tile of polygons (run.visibility_polygons_per_job each), from the
# photos that see the tile; then the merge, a checkpoint: its summary tells the workflow the
# polygon ids (and their sizes and candidate photos), from which the per-polygon jobs are made.


rule visibility_tile:
    input:
        model=SCENE_MODEL,
        photos=f"{R}/photos.json",
        config=STAGE_CFG["visibility"],
    output:
        rows=f"{R}/visibility/tiles/{{tile}}.json",
    params:
        stage_config=STAGE_TEXT["visibility"],
        scene=lambda wc, input: Path(input.model[0]).parent,
        tile=lambda wc: partition.part_spec(wc.tile),
        out_dir=lambda wc, output: Path(output.rows).parent.parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/visibility/{{tile}}.log",
    benchmark:
        f"{R}/benchmarks/visibility_tile/{{tile}}.tsv"
    threads: RUN["scene_threads"]
    resources:
        mem_mb=jobs.scene_mem_mb(SCENE_INPUTS, RUN, factor=8.0),
        runtime=120,
    shell:
        "OMP_NUM_THREADS={threads} difftex visibility --quiet --scene {params.scene:q} "
        "--photos {input.photos:q} --config {input.config} --out-dir {params.out_dir:q} "
        "--tile {params.tile} --rows {output.rows:q} > {log:q} 2>&1"


checkpoint visibility:
    input:
        tiles=expand(f"{R}/visibility/tiles/{{tile}}.json", tile=VISIBILITY_TILES),
    output:
        summary=f"{R}/visibility/summary.json",
    params:
        out_dir=lambda wc, output: Path(output.summary).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/visibility.log",
    benchmark:
        f"{R}/benchmarks/visibility/visibility.tsv"
    resources:
        mem_mb=jobs.gather_mem_mb(len(SCENE_INPUTS), RUN),
        runtime=30,
    shell:
        "difftex visibility --out-dir {params.out_dir:q} --merge {input.tiles:q} > {log:q} 2>&1"

# Visibility masks per spatial tile of polygons (run.visibility_polygons_per_job each), from the
# photos that see the tile; then the merge, a checkpoint: its summary tells the workflow the
# polygon ids (and their sizes and candidate photos), from which the per-polygon jobs are made.


rule visibility_tile:
    input:
        model=SCENE_MODEL,
        photos=str(RES.photos_json),
        config=STAGE_CFG["visibility"],
    output:
        rows=str(RES.visibility_tile("{tile}")),
    params:
        stage_config=STAGE_TEXT["visibility"],
        scene=lambda wc, input: Path(input.model[0]).parent,
        tile=lambda wc: partition.part_spec(wc.tile),
        out_dir=RES.visibility_dir,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("visibility", "{tile}")),
    benchmark:
        str(RES.benchmark("visibility_tile", "{tile}"))
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
        tiles=TILE_ROWS,
    output:
        summary=str(RES.visibility_summary),
    params:
        out_dir=RES.visibility_dir,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("visibility")),
    benchmark:
        str(RES.benchmark("visibility", "visibility"))
    resources:
        mem_mb=jobs.gather_mem_mb(len(SCENE_INPUTS), RUN),
        runtime=30,
    shell:
        "difftex visibility --out-dir {params.out_dir:q} --merge {input.tiles:q} > {log:q} 2>&1"

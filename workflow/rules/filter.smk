# Photo filtering: sharpness, polygons seen and their angles, per photo, in chunks of photos
# (run.filter_photos_per_job each); then the merge decides the kept photos per polygon.


rule filter_part:
    input:
        model=SCENE_MODEL,
        photos=lambda wc: FILTER_PARTS[wc.part],
        config=STAGE_CFG["filter"],
    output:
        str(RES.filter_part("{part}")),
    params:
        stage_config=STAGE_TEXT["filter"],
        scene=lambda wc, input: Path(input.model[0]).parent,
        part=lambda wc: partition.part_spec(wc.part),
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("filter", "{part}")),
    benchmark:
        str(RES.benchmark("filter_part", "{part}"))
    threads: RUN["scene_threads"]
    resources:
        mem_mb=lambda wc, input: jobs.scene_mem_mb(list(input.photos), RUN),
        runtime=60,
    shell:
        "OMP_NUM_THREADS={threads} difftex filter --quiet --scene {params.scene:q} "
        "--config {input.config} --part {params.part} --out {output:q} > {log:q} 2>&1"


rule filter:
    input:
        model=SCENE_MODEL,
        parts=expand(str(RES.filter_part("{part}")), part=FILTER_PARTS),
        config=STAGE_CFG["filter"],
    output:
        table=str(RES.photos_json),
        csv=str(RES.photos_csv),
    params:
        stage_config=STAGE_TEXT["filter"],
        scene=lambda wc, input: Path(input.model[0]).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("filter")),
    benchmark:
        str(RES.benchmark("filter", "filter"))
    resources:
        mem_mb=jobs.gather_mem_mb(len(SCENE_INPUTS), RUN),
        runtime=60,
    shell:
        "difftex filter --quiet --scene {params.scene:q} --config {input.config} "
        "--parts {input.parts:q} --out {output.table:q} > {log:q} 2>&1"

# Photo filtering: sharpness, polygons seen and their angles, per photo, in chunks of photos
# (run.filter_photos_per_job each); then the merge decides the kept photos per polygon.


rule filter_part:
    input:
        model=SCENE_MODEL,
        photos=lambda wc: FILTER_PARTS[wc.part],
        config=STAGE_CFG["filter"],
    output:
        f"{R}/filter/photos-{{part}}.json",
    params:
        stage_config=STAGE_TEXT["filter"],
        scene=lambda wc, input: Path(input.model[0]).parent,
        part=lambda wc: partition.part_spec(wc.part),
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/filter/{{part}}.log",
    benchmark:
        f"{R}/benchmarks/filter_part/{{part}}.tsv"
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
        parts=expand(f"{R}/filter/photos-{{part}}.json", part=FILTER_PARTS),
        config=STAGE_CFG["filter"],
    output:
        table=f"{R}/photos.json",
        csv=f"{R}/photos.csv",
    params:
        stage_config=STAGE_TEXT["filter"],
        scene=lambda wc, input: Path(input.model[0]).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/filter.log",
    benchmark:
        f"{R}/benchmarks/filter/filter.tsv"
    resources:
        mem_mb=jobs.gather_mem_mb(len(SCENE_INPUTS), RUN),
        runtime=60,
    shell:
        "difftex filter --quiet --scene {params.scene:q} --config {input.config} "
        "--parts {input.parts:q} --out {output.table:q} > {log:q} 2>&1"

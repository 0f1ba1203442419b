# Per-polygon stages: `texture` (brightness transfers, blend-weight optimization and composition,
# one pass over each polygon's photos) and `finish` (the PNGs and report from the float texture,
# in the output format; one per texture job). Polygon ids, sizes and candidate photos come from the visibility
# checkpoint, so a cluster runs the polygons in parallel; polygons smaller than run.pack_seconds
# share a texture job (difftex/workflow/jobs.py), named by its polygon or `group-<digest>`. `run.gpu` > 0 requests GPUs; the
# `compute` section (device, torch.compile) changes no result, so changing it reruns nothing.


rule texture:
    input:
        scene=SCENE_MODEL,
        vis=get_job_visibility,
        photos=get_job_photos,
        config=STAGE_CFG["texture"],
        # device and compilation: read, but ancient() and a fixed name keep a change of them
        # from rerunning anything (they change no result beyond float tolerance)
        compute=ancient(f"{R}/config/compute.yaml"),
    output:
        # the job's list of its polygons, written last; each polygon's weights.npz, stats.json and
        # composite.npz are in R/optimized/<polygon>/ (written atomically, one polygon at a time)
        f"{R}/optimized/jobs/{{job}}.json",
    params:
        stage_config=STAGE_TEXT["texture"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dirs=get_job_out_dirs,
        decode_cache_mb=RUN["decode_cache_mb"],
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/texture/{{job}}.log",
    benchmark:
        f"{R}/benchmarks/texture/{{job}}.tsv"
    threads: RUN["polygon_threads"]
    # the longest jobs first (estimated seconds), the short ones around them
    priority: get_job_priority
    resources:
        mem_mb=get_job_mem_mb,
        runtime=get_job_runtime,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex texture --threads {threads} --no-progress --scene {params.scene:q} "
        "--visibility {input.vis:q} --out-dir {params.out_dirs:q} --config {input.config:q} "
        "--compute-config {input.compute:q} --decode-cache-mb {params.decode_cache_mb} --done {output:q} > {log:q} 2>&1"


rule finish:
    input:
        # the texture job; it wrote R/optimized/<pid>/composite.npz of each of its polygons
        job=f"{R}/optimized/jobs/{{job}}.json",
        config=STAGE_CFG["output"],
    output:
        # the job's list of its polygons, written last; each polygon's texture.png, source.png,
        # source.npz, coverage.png and report.json are in R/textures/<polygon>/ (written atomically)
        f"{R}/textures/jobs/{{job}}.json",
    params:
        stage_config=STAGE_TEXT["output"],
        composites=lambda wc: [f"{R}/optimized/{pid}/composite.npz" for pid in get_job_pids(wc)],
        out_dirs=lambda wc: [f"{R}/textures/{pid}" for pid in get_job_pids(wc)],
    log:
        f"{R}/logs/finish/{{job}}.log",
    conda:
        "../envs/difftex.yaml"
    # a shell job that imports no torch (0.2 s), one per texture job (not per polygon: a
    # district's thousands of polygons would be thousands of process starts); a run: job would
    # spawn a second Snakemake (~1.5 s)
    shell:
        "difftex finish --composite {params.composites:q} --config {input.config:q} "
        "--out-dir {params.out_dirs:q} --done {output:q} > {log:q} 2>&1"

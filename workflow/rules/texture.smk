# Per-polygon stages. Polygon ids, sizes and candidate photos come from the visibility checkpoint,
# so a cluster runs the polygons in parallel; polygons smaller than run.pack_seconds share a job
# (difftex/workflow/jobs.py), named by its polygon or `group-<digest>`, in every stage below.
#
# run.split (jobs.split_stages) chooses between
#   initialize -> histmatch -> optimize -> compose: the photos decoded and cropped once
#       (R/init/<pid>/crops.npz), the brightness transfers estimated on those crops
#       (R/histmatch/<pid>/transfers.npz: an input of W, so before the optimization), the
#       optimization from the crops and transfers, the composition (numpy, local); a change of a
#       histmatch_* key reruns histmatch and what follows, one of optimize.lr optimize and what follows;
#   texture: the four in one process (a local CPU run's default: one process start, no crops file).
# Both write the same R/optimized/<pid>/composite.npz (equal arrays; only the report's timings differ),
# so the PNGs that `finish` writes from it are the same bytes.
# The `compute` section (device, torch.compile) changes no result, so changing it reruns nothing.


rule initialize:
    input:
        scene=SCENE_MODEL,
        vis=get_job_visibility,
        photos=get_job_photos,
        config=STAGE_CFG["initialize"],
        # the polygons' height fields from dense geometry (none without it)
        heights=HEIGHT_TILES,
    output:
        # the job's list of its polygons, written last (each R/init/<pid>/crops.npz atomically)
        str(RES.job_file("initialize", "{job}")),
    params:
        heights=HEIGHTS_ARG,
        stage_config=STAGE_TEXT["initialize"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        outs=get_job_init,
        decode_cache_mb=RUN["decode_cache_mb"],
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("initialize", "{job}")),
    benchmark:
        str(RES.benchmark("initialize", "{job}"))
    threads: RUN["polygon_threads"]
    priority: get_job_priority
    resources:
        mem_mb=get_job_mem_mb,
        runtime=get_job_runtime,
    shell:
        "OMP_NUM_THREADS={threads} difftex initialize --threads {threads} --scene {params.scene:q} "
        "--visibility {input.vis:q} --out {params.outs:q} --config {input.config:q} {params.heights}"
        "--decode-cache-mb {params.decode_cache_mb} --done {output:q} > {log:q} 2>&1"


rule histmatch:
    input:
        scene=SCENE_MODEL,
        vis=get_job_visibility,
        init=str(RES.job_file("initialize", "{job}")),
        config=STAGE_CFG["histmatch"],
        # on the optimization's device, so the transfers are the ones the one-process stage finds
        compute=ancient(str(RES.compute_config)),
        # the polygons' height fields from dense geometry (none without it)
        heights=HEIGHT_TILES,
    output:
        # the job's list; each polygon's transfers.npz is in R/histmatch/<polygon>/ (atomically)
        str(RES.job_file("histmatch", "{job}")),
    params:
        heights=HEIGHTS_ARG,
        stage_config=STAGE_TEXT["histmatch"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        crops=get_job_init,
        outs=get_job_transfers,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("histmatch", "{job}")),
    benchmark:
        str(RES.benchmark("histmatch", "{job}"))
    threads: RUN["polygon_threads"]
    priority: get_job_priority
    resources:
        mem_mb=get_job_mem_mb,
        runtime=get_job_runtime,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex histmatch --threads {threads} --scene {params.scene:q} "
        "--visibility {input.vis:q} --init {params.crops:q} --out {params.outs:q} "
        "--config {input.config:q} {params.heights}--compute-config {input.compute:q} --done {output:q} > {log:q} 2>&1"


rule optimize:
    input:
        scene=SCENE_MODEL,
        vis=get_job_visibility,
        init=str(RES.job_file("initialize", "{job}")),
        histmatch=str(RES.job_file("histmatch", "{job}")),
        config=STAGE_CFG["texture"],
        # device and compilation: read, but ancient() and a fixed name keep a change of them
        # from rerunning anything (they change no result beyond float tolerance)
        compute=ancient(str(RES.compute_config)),
        # the polygons' height fields from dense geometry (none without it)
        heights=HEIGHT_TILES,
    output:
        # the job's list; each polygon's weights.npz, optimized.npz and stats.json are in
        # R/optimized/<polygon>/ (written atomically)
        str(RES.job_file("optimize", "{job}")),
    params:
        heights=HEIGHTS_ARG,
        stage_config=STAGE_TEXT["texture"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        crops=get_job_init,
        transfers=get_job_transfers,
        out_dirs=get_job_out_dirs,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("optimize", "{job}")),
    benchmark:
        str(RES.benchmark("optimize", "{job}"))
    threads: RUN["polygon_threads"]
    priority: get_job_priority
    resources:
        mem_mb=get_job_mem_mb,
        runtime=get_job_runtime,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex optimize --threads {threads} --no-progress --scene {params.scene:q} "
        "--visibility {input.vis:q} --init {params.crops:q} --transfers {params.transfers:q} "
        "--out-dir {params.out_dirs:q} --config {input.config:q} {params.heights}--compute-config {input.compute:q} "
        "--done {output:q} > {log:q} 2>&1"


rule compose:
    input:
        str(RES.job_file("optimize", "{job}")),
    output:
        # the job's list; each polygon's composite.npz is in R/optimized/<polygon>/ (atomically)
        str(RES.job_file("compose", "{job}")),
    params:
        out_dirs=get_job_out_dirs,
    log:
        str(RES.log("compose", "{job}")),
    conda:
        "../envs/difftex.yaml"
    # numpy only, no torch: a local job of a fraction of a second per polygon
    shell:
        "difftex compose --optimized {params.out_dirs:q} --done {output:q} > {log:q} 2>&1"


rule texture:
    input:
        scene=SCENE_MODEL,
        vis=get_job_visibility,
        photos=get_job_photos,
        config=STAGE_CFG["texture"],
        compute=ancient(str(RES.compute_config)),
        # the polygons' height fields from dense geometry (none without it)
        heights=HEIGHT_TILES,
    output:
        # the job's list of its polygons, written last; each polygon's weights.npz, stats.json and
        # composite.npz are in R/optimized/<polygon>/ (written atomically, one polygon at a time)
        str(RES.job_file("texture", "{job}")),
    params:
        heights=HEIGHTS_ARG,
        stage_config=STAGE_TEXT["texture"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dirs=get_job_out_dirs,
        decode_cache_mb=RUN["decode_cache_mb"],
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("texture", "{job}")),
    benchmark:
        str(RES.benchmark("texture", "{job}"))
    threads: RUN["polygon_threads"]
    # the longest jobs first (estimated seconds), the short ones around them
    priority: get_job_priority
    resources:
        mem_mb=get_job_mem_mb,
        runtime=get_job_runtime,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex texture --threads {threads} --no-progress --scene {params.scene:q} "
        "--visibility {input.vis:q} --out-dir {params.out_dirs:q} --config {input.config:q} {params.heights}"
        "--compute-config {input.compute:q} --decode-cache-mb {params.decode_cache_mb} --done {output:q} > {log:q} 2>&1"


rule finish:
    input:
        # the compose or texture job; it wrote R/optimized/<pid>/composite.npz of each of its polygons
        job=get_composed_job,
        config=STAGE_CFG["output"],
    output:
        # the job's list of its polygons, written last; each polygon's texture.png, source.png,
        # source.npz, coverage.png and report.json are in R/textures/<polygon>/ (written atomically)
        str(RES.job_file("finish", "{job}")),
    params:
        stage_config=STAGE_TEXT["output"],
        composites=lambda wc: [str(RES.composite(pid)) for pid in get_job_pids(wc)],
        out_dirs=lambda wc: [str(RES.polygon_textures(pid)) for pid in get_job_pids(wc)],
    log:
        str(RES.log("finish", "{job}")),
    conda:
        "../envs/difftex.yaml"
    # a shell job that imports no torch (0.2 s), one per texture job (not per polygon: a
    # district's thousands of polygons would be thousands of process starts); a run: job would
    # spawn a second Snakemake (~1.5 s)
    shell:
        "difftex finish --composite {params.composites:q} --config {input.config:q} "
        "--out-dir {params.out_dirs:q} --done {output:q} > {log:q} 2>&1"

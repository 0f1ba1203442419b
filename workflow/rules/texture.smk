# Per-polygon stages: `texture` (brightness transfers, blend-weight optimization and composition,
# one pass over the polygon's photos) and `finish` (the PNGs and report from the float texture,
# in the output format). Polygon ids, sizes and candidate photos come from the visibility
# checkpoint, so a cluster runs the polygons in parallel. `run.gpu` > 0 requests GPUs; the
# `compute` section (device, torch.compile) changes no result, so changing it reruns nothing.


rule texture:
    input:
        scene=SCENE_MODEL,
        vis=f"{R}/visibility/{{pid}}.npz",
        photos=get_polygon_photos,
        config=STAGE_CFG["texture"],
        # device and compilation: read, but ancient() and a fixed name keep a change of them
        # from rerunning anything (they change no result beyond float tolerance)
        compute=ancient(f"{R}/config/compute.yaml"),
    output:
        weights=f"{R}/optimized/{{pid}}/weights.npz",
        stats=f"{R}/optimized/{{pid}}/stats.json",
        composite=f"{R}/optimized/{{pid}}/composite.npz",
    params:
        stage_config=STAGE_TEXT["texture"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dir=lambda wc, output: Path(output.weights).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/texture/{{pid}}.log",
    benchmark:
        f"{R}/benchmarks/texture/{{pid}}.tsv"
    threads: RUN["polygon_threads"]
    resources:
        mem_mb=get_polygon_mem_mb,
        runtime=get_polygon_runtime,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex texture --threads {threads} --no-progress --scene {params.scene:q} "
        "--visibility {input.vis:q} --config {input.config:q} --compute-config {input.compute:q} "
        "--out-dir {params.out_dir:q} > {log:q} 2>&1"


rule finish:
    input:
        composite=f"{R}/optimized/{{pid}}/composite.npz",
        config=STAGE_CFG["output"],
    output:
        texture=f"{R}/textures/{{pid}}/texture.png",
        source=f"{R}/textures/{{pid}}/source.png",
        dominant=f"{R}/textures/{{pid}}/source.npz",
        coverage=f"{R}/textures/{{pid}}/coverage.png",
        report=f"{R}/textures/{{pid}}/report.json",
    params:
        stage_config=STAGE_TEXT["output"],
        out_dir=lambda wc, output: Path(output.texture).parent,
    log:
        f"{R}/logs/finish/{{pid}}.log",
    # a shell job that imports no torch (0.2 s): a run: job would spawn a second Snakemake (~1.5 s)
    shell:
        "difftex finish --composite {input.composite:q} --config {input.config:q} "
        "--out-dir {params.out_dir:q} > {log:q} 2>&1"

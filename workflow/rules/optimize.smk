# Per-polygon stages, one job per polygon and stage: initialization, optimization, histogram
# matching. The polygon ids, sizes and candidate photos come from the visibility checkpoint, so
# a cluster runs the polygons in parallel. `run.gpu` > 0 requests GPUs for these jobs.


rule init:
    input:
        scene=SCENE_MODEL,
        vis=f"{R}/visibility/{{pid}}.npz",
        photos=lambda wc: wf.photo_paths(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid)
        ),
        config=STAGE_CFG["optimize"],
    output:
        f"{R}/init/{{pid}}.npz",
    params:
        stage_config=STAGE_TEXT["optimize"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/init/{{pid}}.log",
    benchmark:
        f"{R}/benchmarks/init/{{pid}}.tsv"
    threads: RUN["polygon_threads"]
    resources:
        mem_mb=lambda wc: wf.polygon_mem_mb(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid), RUN,
            config["optimize"]["top_k"],
        ),
        runtime=30,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex init --threads {threads} --scene {params.scene} --visibility {input.vis} "
        "--config {input.config} --out {output} > {log} 2>&1"


rule optimize:
    input:
        scene=SCENE_MODEL,
        vis=f"{R}/visibility/{{pid}}.npz",
        init=f"{R}/init/{{pid}}.npz",
        photos=lambda wc: wf.photo_paths(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid)
        ),
        config=STAGE_CFG["optimize"],
    output:
        weights=f"{R}/optimized/{{pid}}/weights.npz",
        stats=f"{R}/optimized/{{pid}}/stats.json",
    params:
        stage_config=STAGE_TEXT["optimize"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dir=lambda wc, output: Path(output.weights).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/optimize/{{pid}}.log",
    benchmark:
        f"{R}/benchmarks/optimize/{{pid}}.tsv"
    threads: RUN["polygon_threads"]
    resources:
        mem_mb=lambda wc: wf.polygon_mem_mb(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid), RUN,
            config["optimize"]["top_k"],
        ),
        runtime=lambda wc: wf.polygon_runtime_min(
            wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid), config
        ),
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex optimize --threads {threads} --no-progress --scene {params.scene} --visibility {input.vis} "
        "--init {input.init} --config {input.config} --out-dir {params.out_dir} > {log} 2>&1"


rule histmatch:
    input:
        scene=SCENE_MODEL,
        vis=f"{R}/visibility/{{pid}}.npz",
        weights=f"{R}/optimized/{{pid}}/weights.npz",
        stats=f"{R}/optimized/{{pid}}/stats.json",
        photos=lambda wc: wf.photo_paths(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid)
        ),
        config=STAGE_CFG["optimize"],
    output:
        texture=f"{R}/textures/{{pid}}/texture.png",
        source=f"{R}/textures/{{pid}}/source.png",
        report=f"{R}/textures/{{pid}}/report.json",
    params:
        stage_config=STAGE_TEXT["optimize"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        optimized=lambda wc, input: Path(input.weights).parent,
        out_dir=lambda wc, output: Path(output.texture).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/histmatch/{{pid}}.log",
    benchmark:
        f"{R}/benchmarks/histmatch/{{pid}}.tsv"
    threads: RUN["polygon_threads"]
    resources:
        mem_mb=lambda wc: wf.polygon_mem_mb(
            SCENE, wf.polygon_row(checkpoints.visibility.get().output.summary, wc.pid), RUN,
            config["optimize"]["top_k"],
        ),
        runtime=30,
        gpu=RUN["gpu"],
    shell:
        "OMP_NUM_THREADS={threads} difftex histmatch --threads {threads} --scene {params.scene} --visibility {input.vis} "
        "--optimized {params.optimized} --config {input.config} --out-dir {params.out_dir} > {log} 2>&1"

# Relief from the scene's dense geometry (docs/dense.md): per visibility tile, each polygon's
# height field along its normal, from a cloud, a mesh or COLMAP depth maps, read once per tile.
# Only when the scene has dense geometry (DENSE), or the dense_stereo rule makes depth maps
# (STEREO); the per-polygon stages take the tiles' lists as inputs and map the photos through the fields.


rule heights:
    input:
        rows=str(RES.visibility_tile("{tile}")),
        dense=wf.dense_inputs(DENSE) if DENSE else str(RES.dense_done),
        config=STAGE_CFG["heights"],
    output:
        # the tile's list of its polygons; each R/heights/<pid>.npz is written atomically before it
        str(RES.heights_tile("{tile}")),
    params:
        stage_config=STAGE_TEXT["heights"],
        scene=SCENE,
        source=DENSE.path if DENSE else RES.dense_dir,
        out_dir=RES.heights_dir,
        vis_dir=RES.visibility_dir,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("heights", "{tile}")),
    benchmark:
        str(RES.benchmark("heights", "{tile}"))
    threads: RUN["scene_threads"]
    resources:
        mem_mb=jobs.scene_mem_mb(SCENE_INPUTS, RUN, factor=8.0),
        runtime=60,
    shell:
        "OMP_NUM_THREADS={threads} difftex heights --scene {params.scene:q} --rows {input.rows:q} "
        "--visibility-dir {params.vis_dir:q} --config {input.config:q} --source {params.source:q} "
        "--out-dir {params.out_dir:q} --done {output:q} > {log:q} 2>&1"

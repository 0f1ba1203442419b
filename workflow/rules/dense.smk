# COLMAP PatchMatch stereo on a GPU (docs/dense.md, "Dense stereo on a GPU"): the scene's photos
# undistorted into a COLMAP dense workspace R/dense/ and their depth maps
# (stereo/depth_maps/*.geometric.bin), where the scene has no dense geometry of its own.
# Wanted by `all` only with dense.stereo: true, dense.source: auto and no <scene>/dense/ folder.
# Without CUDA in pycolmap the job warns in one line, and R/dense/ holds only its record saying so.

import difftex.scene.mvs as mvs

# the workspace's record, asked for by `all` (empty: the rule does not run)
DENSE_STEREO = [str(RES.dense_done)] if STEREO else []
# whether pycolmap has CUDA, a parameter of the rule: a run skipped for want of it runs again once
# pycolmap-cuda12 is installed (asked only when the rule is wanted: importing pycolmap takes a while)
DENSE_STEREO_CUDA = mvs.cuda_available() if DENSE_STEREO else False
# photos: visible matches the photos the filter kept (its table is then an input)
DENSE_STEREO_PHOTOS = [str(RES.photos_json)] if config["dense"]["photos"] == "visible" else []


rule dense_stereo:
    input:
        scene=SCENE_INPUTS,
        photos=DENSE_STEREO_PHOTOS,
        config=STAGE_CFG["dense"],
    output:
        # the record, written into the workspace before it is renamed into place
        str(RES.dense_done),
    params:
        stage_config=STAGE_TEXT["dense"],
        # the proxy's folder (the first of the scene's inputs)
        scene=lambda wc, input: Path(input.scene[0]).parent,
        out_dir=RES.dense_dir,
        cuda=DENSE_STEREO_CUDA,
        photos=" ".join(f"--photos '{p}'" for p in DENSE_STEREO_PHOTOS),
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("dense_stereo")),
    benchmark:
        str(RES.benchmark("dense_stereo", "dense_stereo"))
    threads: RUN["scene_threads"]
    resources:
        # PatchMatch's cache of photos and maps (difftex.scene.mvs.CACHE_GB) and a working set
        mem_mb=RUN["base_mem_mb"] + 12000,
        runtime=240,
        gpu=1,
    shell:
        "OMP_NUM_THREADS={threads} difftex dense --scene {params.scene:q} --out {params.out_dir:q} "
        "--config {input.config:q} {params.photos} --done {output:q} > {log:q} 2>&1"

# The textured model: atlas pages, OBJ + MTL + PNG and GLB, with assemble.tileset a 3D Tiles
# tileset; every polygon of the proxy is in it, those no photo sees with a grey patch. Then the
# reports: report.md (summary, stage times) and report/index.html (difftex report: what is
# untextured and why, the model view, metrics, maps with their source legend, texel sizes, loss
# curves and per-level diagnostics, the photo filter table).


rule assemble:
    input:
        scene=SCENE_MODEL,
        summary=str(RES.visibility_summary),
        textures=get_textures,
        config=STAGE_CFG["assemble"],
    output:
        summary=str(RES.model_summary),
        obj=str(RES.model_file(".obj")),
        mtl=str(RES.model_file(".mtl")),
        **({"glb": str(RES.model_file(".glb"))} if config["assemble"]["glb"] else {}),
        # 3D Tiles 1.1 (with its tiles/<building>.glb beside it; docs/tiles.md)
        **({"tileset": str(RES.tileset)} if config["assemble"]["tileset"] else {}),
    params:
        stage_config=STAGE_TEXT["assemble"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        textures=str(RES.textures_dir),
        visibility=RES.visibility_dir,
        out_dir=RES.model_dir,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("assemble")),
    benchmark:
        str(RES.benchmark("assemble", "assemble"))
    threads: 1
    resources:
        mem_mb=get_assemble_mem_mb,
        runtime=60,
    shell:
        "difftex assemble --scene {params.scene:q} --textures {params.textures} "
        "--visibility {params.visibility} --config {input.config} --out-dir {params.out_dir} > {log} 2>&1"


rule report:
    input:
        model=str(RES.model_summary),
        metrics=[str(RES.metrics)] if EVALUATE else [],
    output:
        str(RES.report_md),
    params:
        results=RES.root,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("report")),
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    script:
        "../scripts/report.py"


rule html_report:
    input:
        summary=str(RES.visibility_summary),
        photos=str(RES.photos_json),
        textures=get_textures,
        # the untextured polygons' reasons and the model view
        model=str(RES.model_summary),
        metrics=[str(RES.metrics)] if EVALUATE else [],
    output:
        str(RES.report_html),
    params:
        results=RES.root,
        scene=SCENE,
    conda:
        "../envs/difftex.yaml"
    log:
        str(RES.log("html_report")),
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "difftex report --results {params.results} --scene {params.scene:q} --out {output} > {log} 2>&1"

# The textured model: atlas pages, OBJ + MTL + PNG and GLB, with assemble.tileset a 3D Tiles
# tileset; every polygon of the proxy is in it, those no photo sees with a grey patch. Then the
# reports: report.md (summary, stage times) and report/index.html (difftex report: what is
# untextured and why, the model view, metrics, maps with their source legend, texel sizes, loss
# curves and per-level diagnostics, the photo filter table).


rule assemble:
    input:
        scene=SCENE_MODEL,
        summary=f"{R}/visibility/summary.json",
        textures=get_textures,
        config=STAGE_CFG["assemble"],
    output:
        summary=f"{R}/model/summary.json",
        obj=f"{R}/model/model.obj",
        mtl=f"{R}/model/model.mtl",
        **({"glb": f"{R}/model/model.glb"} if config["assemble"]["glb"] else {}),
        # 3D Tiles 1.1 (with its tiles/<building>.glb beside it; docs/tiles.md)
        **({"tileset": f"{R}/model/tileset/tileset.json"} if config["assemble"]["tileset"] else {}),
    params:
        stage_config=STAGE_TEXT["assemble"],
        scene=lambda wc, input: Path(input.scene[0]).parent,
        textures=f"{R}/textures",
        visibility=lambda wc, input: Path(input.summary).parent,
        out_dir=lambda wc, output: Path(output.summary).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/assemble.log",
    benchmark:
        f"{R}/benchmarks/assemble/assemble.tsv"
    threads: 1
    resources:
        mem_mb=get_assemble_mem_mb,
        runtime=60,
    shell:
        "difftex assemble --scene {params.scene:q} --textures {params.textures} "
        "--visibility {params.visibility} --config {input.config} --out-dir {params.out_dir} > {log} 2>&1"


rule report:
    input:
        model=f"{R}/model/summary.json",
        metrics=[f"{R}/evaluation/metrics.json"] if EVALUATE else [],
    output:
        f"{R}/report.md",
    params:
        results=lambda wc, output: Path(output[0]).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/report.log",
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    script:
        "../scripts/report.py"


rule html_report:
    input:
        summary=f"{R}/visibility/summary.json",
        photos=f"{R}/photos.json",
        textures=get_textures,
        # the untextured polygons' reasons and the model view
        model=f"{R}/model/summary.json",
        metrics=[f"{R}/evaluation/metrics.json"] if EVALUATE else [],
    output:
        f"{R}/report/index.html",
    params:
        results=lambda wc, input: Path(input.summary).parent.parent,
        scene=SCENE,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{R}/logs/html_report.log",
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "difftex report --results {params.results} --scene {params.scene:q} --out {output} > {log} 2>&1"

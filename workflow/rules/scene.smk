# The bundled example: a small synthetic building, generated on first use (seconds to minutes).


rule synth_example:
    output:
        proxy=f"{wf.EXAMPLE_SCENE}/proxy.obj",
        manifest=f"{wf.EXAMPLE_SCENE}/synth.json",
    params:
        out=lambda wc, output: Path(output.proxy).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{config['results']}/logs/synth_example.log",
    benchmark:
        f"{config['results']}/benchmarks/synth_example.tsv"
    threads: 4
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "difftex synth --preset tiny --out {params.out} > {log} 2>&1"
